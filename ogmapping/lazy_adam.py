"""Adam over the rows of the hash table that a step actually touched (lazy Adam).

The dense version's hash table holds levels x 2^19 rows, of which one iteration reads a few
hundred thousand. Dense Adam rewrote all of them every step and autograd built a dense gradient
of the whole table (~140 ms per iteration at 320x240 on two cores). Here the gathers' backward
deposits (row, gradient) pairs in a ``RowGradients`` sink instead of a gradient tensor (a sparse
gradient would be summed by autograd across the window's views: a sort per view), and the step
updates the moments and values of the touched rows only, with the global step count for bias
correction (TensorFlow's LazyAdam): rows that are not read keep their moments instead of decaying.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange


class RowGradients:
    """Gradient rows of one table, as deposited by backward passes since the last ``clear``."""

    def __init__(self) -> None:
        self.rows: list[torch.Tensor] = []
        self.values: list[torch.Tensor] = []

    def add(self, rows: torch.Tensor, values: torch.Tensor) -> None:
        self.rows.append(rows.reshape(-1))
        self.values.append(values.reshape(rows.numel(), -1))

    def clear(self) -> None:
        self.rows, self.values = [], []

    def summed(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """Unique flat rows (sorted) and their summed gradients; None when nothing was deposited."""
        if not self.rows:
            return None
        rows, inverse = torch.unique(torch.cat(self.rows), return_inverse=True)
        values = torch.cat(self.values)
        return rows, values.new_zeros(rows.numel(), values.shape[1]).index_add_(0, inverse, values)

    def dense(self, shape: torch.Size) -> torch.Tensor:
        """The same gradient as a dense tensor of the table's shape (for tests)."""
        total = torch.zeros(shape[0] * shape[1], shape[2])
        summed = self.summed()
        if summed is not None:
            total.index_add_(0, *summed)
        return total.view(shape)


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


class LazyAdam:
    """Adam (as ``torch.optim.Adam``, no weight decay) applied to the rows ``gradients`` holds.

    ``compiled`` steps with one Numba pass (a float32 CPU table) instead of torch ops.
    """

    def __init__(self, table: torch.nn.Parameter, gradients: RowGradients, lr: float, *, compiled: bool,
                 betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-15) -> None:
        self.table = table
        self.compiled = compiled
        self.gradients = gradients
        self.lr = lr
        self.betas = betas
        self.eps = eps
        self.step_count = 0
        self.exp_avg = torch.zeros_like(table)
        self.exp_avg_sq = torch.zeros_like(table)

    def zero_grad(self) -> None:
        self.gradients.clear()

    @torch.no_grad()
    def step(self) -> None:
        summed = self.gradients.summed()
        if summed is None:
            return
        rows, values = summed
        self.step_count += 1
        width = self.table.shape[-1]
        beta1, beta2 = self.betas
        correction1 = 1 - beta1**self.step_count
        correction2 = 1 - beta2**self.step_count
        table = self.table.view(-1, width)
        exp_avg = self.exp_avg.view(-1, width)
        exp_avg_sq = self.exp_avg_sq.view(-1, width)
        if self.compiled:
            _adam_rows(table.numpy(), exp_avg.numpy(), exp_avg_sq.numpy(), rows.numpy(),
                       values.contiguous().numpy(), self.lr / correction1, correction2, beta1, beta2, self.eps)
            return
        first = exp_avg.index_select(0, rows).mul_(beta1).add_(values, alpha=1 - beta1)
        second = exp_avg_sq.index_select(0, rows).mul_(beta2).addcmul_(values, values, value=1 - beta2)
        exp_avg.index_copy_(0, rows, first)
        exp_avg_sq.index_copy_(0, rows, second)
        denominator = (second / correction2).sqrt_().add_(self.eps)
        table.index_add_(0, rows, first.div_(denominator), alpha=-self.lr / correction1)


@njit(parallel=True, cache=True)
def _adam_rows(table, exp_avg, exp_avg_sq, rows, values, step_size, correction2, beta1, beta2, eps):
    """The same update as the torch path, one pass over the (unique) touched rows on the CPU."""
    for i in prange(rows.shape[0]):
        row = rows[i]
        for j in range(table.shape[1]):
            g = values[i, j]
            m = beta1 * exp_avg[row, j] + (1.0 - beta1) * g
            v = beta2 * exp_avg_sq[row, j] + (1.0 - beta2) * g * g
            exp_avg[row, j] = m
            exp_avg_sq[row, j] = v
            table[row, j] -= step_size * m / (np.sqrt(v / correction2) + eps)

