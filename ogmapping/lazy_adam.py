"""Adam over the rows of the hash table that a step actually touched (lazy Adam).

The dense version's hash table holds levels x 2^19 rows, of which one iteration reads a few
hundred thousand. Dense Adam rewrote all of them every step and autograd built a dense gradient
of the whole table (~140 ms per iteration at 320x240 on two cores). Here the gather's backward
returns a sparse gradient (as ``nn.Embedding(sparse=True)`` does) and the step updates the moments
and values of the touched rows only, with the global step count for bias correction (TensorFlow's
LazyAdam): rows that are not read keep their moments instead of decaying them.
"""

from __future__ import annotations

import numpy as np
import torch
from numba import njit, prange


class SparseRowGather(torch.autograd.Function):
    """``table.view(-1, F)[rows]`` whose gradient for ``table`` (L, T, F) is a sparse COO tensor."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(rows)
        ctx.shape = table.shape
        return table.view(-1, table.shape[-1]).index_select(0, rows)

    @staticmethod
    def backward(ctx, grad: torch.Tensor) -> tuple[torch.Tensor, None]:
        (rows,) = ctx.saved_tensors
        size = ctx.shape[1]
        indices = torch.stack([torch.div(rows, size, rounding_mode="floor"), rows % size])
        return torch.sparse_coo_tensor(indices, grad, ctx.shape, check_invariants=False), None


class LazyAdam:
    """Adam (as ``torch.optim.Adam``, no weight decay) applied row-wise to a table with sparse grads."""

    def __init__(self, table: torch.nn.Parameter, lr: float, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-15) -> None:
        self.table = table
        self.lr = lr
        self.betas = betas
        self.eps = eps
        self.step_count = 0
        self.exp_avg = torch.zeros_like(table)
        self.exp_avg_sq = torch.zeros_like(table)

    def zero_grad(self) -> None:
        self.table.grad = None

    @torch.no_grad()
    def step(self) -> None:
        grad = self.table.grad
        if grad is None:
            return
        self.step_count += 1
        width = self.table.shape[-1]
        if grad.is_sparse:
            # Uncoalesced entries (one per lookup); unique + index_add is ~5x faster than coalesce().
            level, row = grad._indices()
            rows, inverse = torch.unique(level * self.table.shape[1] + row, return_inverse=True)
            values = grad._values().new_zeros(rows.numel(), width).index_add_(0, inverse, grad._values())
        else:
            rows = torch.nonzero(grad.reshape(-1, width).abs().sum(-1)).squeeze(-1)
            values = grad.reshape(-1, width)[rows]
        beta1, beta2 = self.betas
        correction1 = 1 - beta1**self.step_count
        correction2 = 1 - beta2**self.step_count
        table = self.table.view(-1, width)
        exp_avg = self.exp_avg.view(-1, width)
        exp_avg_sq = self.exp_avg_sq.view(-1, width)
        if table.device.type == "cpu" and table.dtype == torch.float32:
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
