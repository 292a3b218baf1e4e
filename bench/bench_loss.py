"""Time the mapping loss's image terms, forward+backward: autograd definitions against the fused pass.

Both compute colour L1, 1 - SSIM (cached ground-truth statistics, as the mapper does) and depth
L1 on the same random images in one process; each timing is the median over ``--repeats`` runs
after a warm-up, the two interleaved. Also prints the largest relative gradient difference.

    .venv/bin/python bench/bench_loss.py
    .venv/bin/python bench/bench_loss.py --resolutions 320x240 --repeats 50
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import ogmapping  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its thread pool)

# isort: split
import numba
import torch

from ogmapping.optim.fused_loss import image_terms
from ogmapping.optim.losses import depth_l1
from ogmapping.optim.ssim import reference_statistics, ssim_map

Terms = Callable[[torch.Tensor, torch.Tensor], tuple[torch.Tensor, ...]]


def _autograd_terms(gt_color: torch.Tensor, gt_depth: torch.Tensor) -> Terms:
    reference = reference_statistics(gt_color, compiled=True)
    return lambda color, depth: (
        (color - gt_color).abs().mean(),
        1.0 - ssim_map(color, gt_color, reference, compiled=False).mean(),
        depth_l1(depth, gt_depth),
    )


def _fused_terms(gt_color: torch.Tensor, gt_depth: torch.Tensor) -> Terms:
    reference = reference_statistics(gt_color, compiled=True)
    return lambda color, depth: image_terms(color, depth, gt_color, gt_depth, reference)


def _time(terms: Terms, color: torch.Tensor, depth: torch.Tensor) -> tuple[float, torch.Tensor]:
    color.grad, depth.grad = None, None
    start = time.perf_counter()
    sum(terms(color, depth)).backward()
    return time.perf_counter() - start, color.grad.clone()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolutions", default="160x120,320x240,640x480", help="comma-separated WxH")
    parser.add_argument("--repeats", type=int, default=30, help="timed runs per case (default 30)")
    args = parser.parse_args()
    print(f"torch {torch.__version__} ({torch.get_num_threads()} threads), numba {numba.__version__} "
          f"({numba.get_num_threads()} threads)\n")
    print("| resolution | autograd fwd+bwd ms | fused fwd+bwd ms | speed-up | max rel. gradient difference |")
    print("|---|---|---|---|---|")
    for resolution in args.resolutions.split(","):
        width, height = (int(v) for v in resolution.split("x"))
        g = torch.Generator().manual_seed(0)
        gt_color = torch.rand(height, width, 3, generator=g)
        gt_depth = 0.5 + 3.0 * torch.rand(height, width, generator=g)
        color = (0.7 * gt_color + 0.3 * torch.rand(height, width, 3, generator=g)).requires_grad_()
        depth = (gt_depth + 0.1 * torch.randn(height, width, generator=g)).requires_grad_()
        cases = {"autograd": _autograd_terms(gt_color, gt_depth), "fused": _fused_terms(gt_color, gt_depth)}
        times: dict[str, list[float]] = {name: [] for name in cases}
        grads = {name: _time(terms, color, depth)[1] for name, terms in cases.items()}  # warm-up
        for _ in range(args.repeats):
            for name, terms in cases.items():
                times[name].append(_time(terms, color, depth)[0])
        slow, fast = (statistics.median(times[name]) * 1000 for name in cases)
        difference = float((grads["fused"] - grads["autograd"]).abs().max() / grads["autograd"].abs().max())
        print(f"| {resolution} | {slow:.2f} | {fast:.2f} | {slow / fast:.1f}x | {difference:.1e} |")


if __name__ == "__main__":
    main()
