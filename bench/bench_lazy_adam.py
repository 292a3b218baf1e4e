"""Lazy Adam over the dense hash table: one step's cost against torch.optim.Adam over the whole table.

A view of a dense map reads ~4000 anchors x 8 levels x 8 corners rows of the 8 x 2^19 x 4 table;
this times the gather's forward+backward and the optimiser step for both ways (median of 20).

    .venv/bin/python bench/bench_lazy_adam.py
"""

from __future__ import annotations

import statistics
import time

import ogmapping  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its thread pool)

# isort: split
import torch

from ogmapping.model.row_gradients import RowGradients, SparseRowGather
from ogmapping.optim.lazy_adam import LazyAdam

LEVELS, SIZE, FEATURES, ANCHORS, REPEATS = 8, 2**19, 4, 4000, 20


def median_ms(samples: list[float]) -> float:
    return statistics.median(samples) * 1000


def main() -> None:
    generator = torch.Generator().manual_seed(0)
    rows = torch.randint(0, SIZE, (ANCHORS, LEVELS, 8), generator=generator)
    rows = (rows + torch.arange(LEVELS).view(1, LEVELS, 1) * SIZE).reshape(-1)
    start = torch.randn(LEVELS, SIZE, FEATURES, generator=generator) * 1e-4
    for name in ("lazy", "dense"):
        table = torch.nn.Parameter(start.clone())
        sink = RowGradients()
        optimizer = (LazyAdam(table, sink, 0.01, compiled=True) if name == "lazy"
                     else torch.optim.Adam([table], lr=0.01, eps=1e-15))
        forward_backward, step = [], []
        for _ in range(REPEATS):
            tic = time.perf_counter()
            values = SparseRowGather.apply(table, rows, sink) if name == "lazy" else table.view(-1, FEATURES)[rows]
            values.sum().backward()
            toc = time.perf_counter()
            optimizer.step()
            optimizer.zero_grad()
            forward_backward.append(toc - tic)
            step.append(time.perf_counter() - toc)
        print(f"{name:5s} Adam: gather fwd+bwd {median_ms(forward_backward):6.1f} ms, step {median_ms(step):6.1f} ms "
              f"({rows.numel()} lookups, {torch.get_num_threads()} threads)")


if __name__ == "__main__":
    main()
