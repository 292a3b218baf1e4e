"""The hash table's gradient as the rows a step touched: a sink the encoding's gathers fill.

The dense version's hash table holds levels x 2^19 rows, of which one iteration reads a few
hundred thousand. Dense Adam over all of them and autograd's dense gradient of the whole table cost
~140 ms per iteration at 320x240 on two cores, so the gathers' backward deposits the table's gradient
in a ``RowGradients`` sink instead of a gradient tensor (a sparse gradient would be summed by autograd
across the window's views: a sort per view), and ``optim.lazy_adam.LazyAdam`` steps the touched rows
only.

The sink takes (row, gradient) pairs from the torch gathers, and summing those is a sort of every
lookup (``torch.unique``: 22 ms of a 320x240 dense step, a third of the dense preset's time). The
compiled encoding instead sums its lookups in place into a table-shaped buffer (``TouchedRows``)
that flags the rows it touched, and the compiled step walks the flagged rows, so nothing sorts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from numba import get_num_threads, njit, prange


@dataclass
class TouchedRows:
    """A table-shaped gradient summed in place, and which rows were touched since the last reset.

    ``values`` is zero outside the touched rows. The step finds them by a scan of ``flags`` (a
    byte per row, a few MB), which walks the table in memory order: a list of the touched rows in
    first-touch order made the step's row accesses random and cost it twice the time.
    """

    values: np.ndarray  # (levels * size, F) float32
    flags: np.ndarray  # (levels * size,) uint8: 1 where touched
    counts: np.ndarray  # (levels,) int64: rows touched per level
    size: int  # rows per level

    @classmethod
    def for_table(cls, shape: torch.Size) -> TouchedRows:
        levels, size, width = shape
        return cls(np.zeros((levels * size, width), np.float32), np.zeros(levels * size, np.uint8),
                   np.zeros(levels, np.int64), size)

    def rows(self) -> np.ndarray:
        """The touched rows, sorted."""
        return np.flatnonzero(self.flags)

    def reset(self) -> None:
        if self.counts.any():
            _reset(self.values, self.flags, self.counts, get_num_threads())


class RowGradients:
    """The gradient of one table as deposited by backward passes since the last ``clear``: (row,
    gradient) pairs from ``add``, and lookups summed in place by ``accumulate_lookups``."""

    def __init__(self) -> None:
        self.rows: list[torch.Tensor] = []
        self.values: list[torch.Tensor] = []
        self.touched: TouchedRows | None = None

    def add(self, rows: torch.Tensor, values: torch.Tensor) -> None:
        self.rows.append(rows.reshape(-1))
        self.values.append(values.reshape(rows.numel(), -1))

    def accumulate_lookups(self, shape: torch.Size, rows: np.ndarray, weights: np.ndarray, grad: np.ndarray) -> None:
        """Add ``grad[m, level * F:(level + 1) * F] * weights[m, level, k]`` to row ``rows[m, level, k]``
        of a table of ``shape`` (levels, size, F) for every lookup, in place (the compiled encoding's
        backward; float32 CPU arrays, ``rows`` flat over the table)."""
        touched = self._touched_for(shape)
        _deposit_lookups(rows, weights, grad, touched.values, touched.flags, touched.counts, get_num_threads())

    def folded(self, shape: torch.Size) -> TouchedRows:
        """Everything deposited, summed in place: pairs from ``add`` are folded into the buffer."""
        touched = self._touched_for(shape)
        if self.rows:
            values = torch.cat(self.values).to(torch.float32).contiguous().numpy()
            _deposit_pairs(torch.cat(self.rows).numpy(), values, touched.values, touched.flags, touched.counts,
                           touched.size)
            self.rows, self.values = [], []
        return touched

    def clear(self) -> None:
        self.rows, self.values = [], []
        if self.touched is not None:
            self.touched.reset()

    def summed(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Unique flat rows (sorted) and their summed gradients; None when nothing was deposited."""
        rows, values = list(self.rows), list(self.values)
        if self.touched is not None and self.touched.counts.any():
            touched_rows = self.touched.rows()
            rows.append(torch.from_numpy(touched_rows))
            values.append(torch.from_numpy(self.touched.values[touched_rows]))
        if not rows:
            return None
        unique, inverse = torch.unique(torch.cat(rows), return_inverse=True)
        values = torch.cat(values)
        return unique, values.new_zeros(unique.numel(), values.shape[1]).index_add_(0, inverse, values)

    def dense(self, shape: torch.Size) -> torch.Tensor:
        """The same gradient as a dense tensor of the table's shape (for tests)."""
        total = torch.zeros(shape[0] * shape[1], shape[2])
        summed = self.summed()
        if summed is not None:
            total.index_add_(0, *summed)
        return total.view(shape)

    def _touched_for(self, shape: torch.Size) -> TouchedRows:
        if self.touched is None:
            self.touched = TouchedRows.for_table(shape)
        elif self.touched.values.shape != (shape[0] * shape[1], shape[2]):
            raise ValueError(f"gradient buffer is for a table of {self.touched.values.shape} rows, not {tuple(shape)}")
        return self.touched


class SparseRowGather(torch.autograd.Function):
    """``table.view(-1, F)[rows]``; the table's gradient goes to ``sink``, not to ``table.grad``."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, rows: torch.Tensor, sink: RowGradients) -> torch.Tensor:
        ctx.save_for_backward(rows)
        ctx.sink = sink
        return table.view(-1, table.shape[-1]).index_select(0, rows)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[None, None, None]:
        (rows,) = ctx.saved_tensors
        ctx.sink.add(rows, grad)
        return None, None, None


# Rows per block of the scans over the whole table (the step, the reset). Blocks and levels are
# dealt to the threads in turn: the fine levels hold most touched rows and are the slow ones to
# sum into (their rows are scattered), so contiguous shares would leave one thread most of the work.
SCAN_BLOCK = 1 << 12


@njit(parallel=True, cache=True, error_model="numpy")
def _deposit_lookups(rows, weights, grad, values, flags, counts, n_threads):
    """``RowGradients.accumulate_lookups``: a level's rows are its own, so each thread sums whole
    levels, each row's lookups in the order they come, as ``index_add_`` over them would."""
    count, levels, corners = weights.shape
    width = values.shape[1]
    for worker in prange(n_threads):
        for level in range(worker, levels, n_threads):
            touched = 0
            for m in range(count):
                for corner in range(corners):
                    row = rows[m, level, corner]
                    touched += 1 - flags[row]
                    flags[row] = 1
                    weight = weights[m, level, corner]
                    for f in range(width):
                        values[row, f] += grad[m, level * width + f] * weight
            counts[level] += touched


@njit(cache=True, error_model="numpy")
def _deposit_pairs(rows, pair_values, values, flags, counts, size):
    """(row, gradient) pairs summed into the buffer, in order."""
    for i in range(rows.shape[0]):
        row = rows[i]
        counts[row // size] += 1 - flags[row]
        flags[row] = 1
        for f in range(values.shape[1]):
            values[row, f] += pair_values[i, f]


@njit(parallel=True, cache=True, error_model="numpy")
def _reset(values, flags, counts, n_threads):
    """Zero the touched rows of the buffer and their flags."""
    blocks = (flags.shape[0] + SCAN_BLOCK - 1) // SCAN_BLOCK
    for worker in prange(n_threads):
        for block in range(worker, blocks, n_threads):
            for row in range(block * SCAN_BLOCK, min(flags.shape[0], (block + 1) * SCAN_BLOCK)):
                if flags[row]:
                    flags[row] = 0
                    values[row, :] = 0.0
    counts[:] = 0
