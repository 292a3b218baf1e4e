"""Time forward+backward of the torch reference and the compiled cpu rasterizer side by side.

Both backends render the same random scene (Gaussians scattered through the camera frustum 1-4 m
away, scales 0.5-5 cm, opacities 0.1-0.9) in one process; each timing is the median over
``--repeats`` (cpu) or ``--ref-repeats`` (torch) runs after a warm-up, the two interleaved.
Every case also checks that the two agree (relative norm error of the images and of every
gradient). Prints a Markdown table; ``--json`` also saves it.

    .venv/bin/python bench/bench_rasterizer.py
    .venv/bin/python bench/bench_rasterizer.py --sizes 50000 --resolutions 320x240 --json out.json
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import time
from pathlib import Path

import ogmapping  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its thread pool)

# isort: split
import numba
import torch

from ogmapping.render import Camera, SplatSet, cpu_backend, torch_backend

PARAMS = ("means", "quats", "scales", "opacities", "colors")


def frustum_scene(n: int, width: int, height: int, seed: int) -> tuple[list[torch.Tensor], torch.Tensor, torch.Tensor]:
    """Random Gaussians whose centres project inside the image, 1-4 m in front of the camera."""
    g = torch.Generator().manual_seed(seed)
    focal = 0.82 * width
    K = torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])
    z = 1.0 + 3.0 * torch.rand(n, generator=g)
    u = torch.rand(n, generator=g) * width
    v = torch.rand(n, generator=g) * height
    means = torch.stack([(u - width / 2) / focal * z, (v - height / 2) / focal * z, z], dim=-1)
    quats = torch.randn(n, 4, generator=g)
    scales = torch.exp(torch.empty(n, 3).uniform_(math.log(0.005), math.log(0.05), generator=g))
    opacities = torch.empty(n).uniform_(0.1, 0.9, generator=g)
    colors = torch.rand(n, 3, generator=g)
    return [means, quats, scales, opacities, colors], torch.eye(4), K


def forward_backward(backend, params, viewmat, K, width, height, weights):
    """One render plus backward of a loss touching colour, depth and alpha; returns time and results."""
    leaves = [p.clone().requires_grad_(True) for p in params]
    start = time.perf_counter()
    out = backend.rasterize(SplatSet(*leaves), Camera(viewmat, K, width, height))
    loss = (out.color * weights[0]).sum() + (out.depth * weights[1]).sum() + (out.alpha * weights[2]).sum()
    loss.backward()
    elapsed = time.perf_counter() - start
    results = {"color": out.color, "depth": out.depth, "alpha": out.alpha, "means2d.grad": out.means2d.grad}
    results.update({f"{name}.grad": leaf.grad for name, leaf in zip(PARAMS, leaves, strict=True)})
    return elapsed, {k: v.detach() for k, v in results.items()}


def relative_error(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a.double() - b.double()).norm() / b.double().norm().clamp_min(1e-30))


def bench_case(n: int, width: int, height: int, args: argparse.Namespace) -> dict:
    params, viewmat, K = frustum_scene(n, width, height, args.seed)
    g = torch.Generator().manual_seed(args.seed + 1)
    weights = (torch.rand(height, width, 3, generator=g), torch.rand(height, width, generator=g),
               torch.rand(height, width, generator=g))
    backends = {"cpu": cpu_backend, "torch": torch_backend}
    for backend in backends.values():
        forward_backward(backend, params, viewmat, K, width, height, weights)
    # Interleave the two backends' runs so load from other processes hits both alike.
    plan = sorted(
        [(i / args.repeats, "cpu") for i in range(args.repeats)]
        + [(i / args.ref_repeats, "torch") for i in range(args.ref_repeats)]
    )
    runs, results = {"cpu": [], "torch": []}, {}
    for _, name in plan:
        elapsed, results[name] = forward_backward(backends[name], params, viewmat, K, width, height, weights)
        runs[name].append(elapsed)
    timings = {name: statistics.median(times) * 1e3 for name, times in runs.items()}
    errors = {key: relative_error(results["cpu"][key], results["torch"][key]) for key in results["torch"]}
    return {
        "gaussians": n, "width": width, "height": height,
        "cpu_ms": timings["cpu"], "torch_ms": timings["torch"], "speedup": timings["torch"] / timings["cpu"],
        "max_rel_error": max(errors.values()), "rel_errors": errors,
        "agree": max(errors.values()) < args.tolerance,
    }


def markdown(rows: list[dict]) -> str:
    lines = [
        "| Gaussians | resolution | torch fwd+bwd (ms) | cpu fwd+bwd (ms) | speedup | max rel. error |",
        "|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['gaussians']:,} | {r['width']}x{r['height']} | {r['torch_ms']:.1f} | {r['cpu_ms']:.1f} "
            f"| {r['speedup']:.1f}x | {r['max_rel_error']:.1e}{'' if r['agree'] else ' (MISMATCH)'} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[5000, 20000, 50000], help="Gaussian counts")
    parser.add_argument("--resolutions", nargs="+", default=["160x120", "320x240"], help="WIDTHxHEIGHT")
    parser.add_argument("--repeats", type=int, default=10, help="timed runs of the cpu backend per case")
    parser.add_argument("--ref-repeats", type=int, default=3, help="timed runs of the torch reference per case")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--tolerance", type=float, default=1e-4, help="max relative error counted as agreement")
    parser.add_argument("--json", type=Path, help="also write the results here")
    args = parser.parse_args()

    rows = []
    for resolution in args.resolutions:
        width, height = (int(x) for x in resolution.lower().split("x"))
        for n in args.sizes:
            rows.append(bench_case(n, width, height, args))
            print(f"done {n} Gaussians at {resolution}: cpu {rows[-1]['cpu_ms']:.1f} ms, "
                  f"torch {rows[-1]['torch_ms']:.1f} ms", flush=True)
    env = (
        f"torch {torch.__version__} ({torch.get_num_threads()} threads), numba {numba.__version__} "
        f"({numba.get_num_threads()} threads, {numba.threading_layer()} layer), "
        f"{platform.processor() or platform.machine()}, OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}, "
        f"load average {os.getloadavg()[0]:.1f} at the end"
    )
    print()
    print(markdown(rows))
    print(f"\n{env}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"environment": env, "results": rows}, indent=2))
    if not all(r["agree"] for r in rows):
        raise SystemExit("backends disagree beyond --tolerance")


if __name__ == "__main__":
    main()
