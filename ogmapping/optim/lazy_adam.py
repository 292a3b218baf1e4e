"""Adam over the rows of the hash table that a step actually touched (lazy Adam).

Dense Adam rewrote every row of the dense version's hash table each step. Here the step updates
the moments and values of the rows the table's ``RowGradients`` sink holds, with the global step
count for bias correction (TensorFlow's LazyAdam): rows that are not read keep their moments
instead of decaying. The compiled step walks the sink's table-shaped buffer of touched rows in
memory order and resets it as it goes.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import get_num_threads, njit, prange

from ogmapping.model.row_gradients import SCAN_BLOCK, RowGradients


class LazyAdam:
    """Adam (as ``torch.optim.Adam``, no weight decay) applied to the rows ``gradients`` holds.

    ``compiled`` steps with one Numba pass over the touched rows (a float32 CPU table) instead of torch ops;
    ``static_shapes`` with torch ops over the whole table, the rows not touched left as they are, instead of
    over the touched rows (whose number the host would wait for).
    """

    def __init__(self, table: torch.nn.Parameter, gradients: RowGradients, lr: float, *, compiled: bool,
                 static_shapes: bool = False, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-15) -> None:
        self.table = table
        self.compiled = compiled
        self.static_shapes = static_shapes
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
        if self.compiled:
            self._compiled_step()
            return
        if self.static_shapes:
            self._masked_step()
            return
        summed = self.gradients.summed()
        if summed is None:
            return
        rows, values = summed
        correction1, correction2 = self._advance()
        beta1, beta2 = self.betas
        table, exp_avg, exp_avg_sq = self._flat()
        first = exp_avg.index_select(0, rows).mul_(beta1).add_(values, alpha=1 - beta1)
        second = exp_avg_sq.index_select(0, rows).mul_(beta2).addcmul_(values, values, value=1 - beta2)
        exp_avg.index_copy_(0, rows, first)
        exp_avg_sq.index_copy_(0, rows, second)
        denominator = (second / correction2).sqrt_().add_(self.eps)
        table.index_add_(0, rows, first.div_(denominator), alpha=-self.lr / correction1)

    def _compiled_step(self) -> None:
        """The same update, one pass over the touched rows, which it leaves reset for the next step."""
        touched = self.gradients.folded(self.table.shape)
        if not touched.counts.any():
            return
        correction1, correction2 = self._advance()
        table, exp_avg, exp_avg_sq = self._flat()
        _adam_touched(table.numpy(), exp_avg.numpy(), exp_avg_sq.numpy(), touched.values, touched.flags,
                      get_num_threads(), self.lr / correction1, correction2, *self.betas, self.eps)
        touched.counts[:] = 0

    def _masked_step(self) -> None:
        """The same update as elementwise ops over the whole table, masked to the rows touched."""
        if not self.gradients.rows:
            return
        table, exp_avg, exp_avg_sq = self._flat()
        grad = torch.zeros_like(table)
        touched = torch.zeros(table.shape[0], 1, dtype=torch.bool, device=table.device)
        for rows, values in zip(self.gradients.rows, self.gradients.values, strict=True):
            grad.index_add_(0, rows, values.to(grad.dtype))
            touched.index_fill_(0, rows, True)
        correction1, correction2 = self._advance()
        beta1, beta2 = self.betas
        first = torch.where(touched, exp_avg.mul(beta1).add_(grad, alpha=1 - beta1), exp_avg)
        second = torch.where(touched, exp_avg_sq.mul(beta2).addcmul_(grad, grad, value=1 - beta2), exp_avg_sq)
        exp_avg.copy_(first)
        exp_avg_sq.copy_(second)
        step = first.div_((second / correction2).sqrt_().add_(self.eps))
        table.add_(torch.where(touched, step, 0.0), alpha=-self.lr / correction1)

    def _advance(self) -> tuple[float, float]:
        """Count a step; Adam's bias corrections 1 - beta1^t and 1 - beta2^t for it."""
        self.step_count += 1
        beta1, beta2 = self.betas
        return 1 - beta1**self.step_count, 1 - beta2**self.step_count

    def _flat(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The table and its moments as (rows, F) views, updated in place."""
        width = self.table.shape[-1]
        return self.table.detach().view(-1, width), self.exp_avg.view(-1, width), self.exp_avg_sq.view(-1, width)


@njit(parallel=True, cache=True)
def _adam_touched(table, exp_avg, exp_avg_sq, values, flags, n_threads, step_size, correction2, beta1, beta2, eps):
    """The torch path's update on every touched row, in memory order; the buffer is reset as it goes."""
    blocks = (flags.shape[0] + SCAN_BLOCK - 1) // SCAN_BLOCK
    for worker in prange(n_threads):
        for block in range(worker, blocks, n_threads):
            for row in range(block * SCAN_BLOCK, min(flags.shape[0], (block + 1) * SCAN_BLOCK)):
                if flags[row] == 0:
                    continue
                for j in range(table.shape[1]):
                    g = values[row, j]
                    m = beta1 * exp_avg[row, j] + (1.0 - beta1) * g
                    v = beta2 * exp_avg_sq[row, j] + (1.0 - beta2) * g * g
                    exp_avg[row, j] = m
                    exp_avg_sq[row, j] = v
                    table[row, j] -= step_size * m / (np.sqrt(v / correction2) + eps)
                    values[row, j] = 0.0
                flags[row] = 0
