"""The rasterizer's options (``render.packed``, ``render.absgrad``, ``render.antialiased``) and selective Adam
(``optim.selective``), each timed on one steady two-view step at 1200x680 with about half a million
Gaussians a view, and what each changes in the output.

The Gaussians come from two frames' depth (frames 0 and 10 of the synthetic room, or of ``--data``, e.g.
Replica room0 with ``--format replica``): ``--gaussians`` of the pixels of both back-projected, each as
wide as the pixels it stands for, its colour and scale perturbed, so the step has something to fit. Each
option set starts from the same Gaussians and runs the same steps: both views rendered in one
``rasterize_batch`` (the engine's renderer, the set's ``RasterOptions``), colour and depth L1 against the
frames, backward, Adam over every Gaussian's parameters as rows (torch's fused Adam, or ``SelectiveAdam``
stepping the Gaussians either view saw). A step's time (forward, backward and optimiser; CUDA events on a
GPU) is the median over ``--steps`` after ``--warmup``; beside it the peak GPU memory, the Gaussians each
view drew, the final render's PSNR against the baseline's (what the option changes in the image) and
against the frames, and the share of drawn Gaussians whose mean screen-space gradient over the timed
steps reaches ``refine.grad_threshold``'s default: what growth would read (the absolute gradient with
``absgrad``).

    python bench/gpu/raster_options.py --out DIR                    # synthetic room, CUDA, 1200x680
    python bench/gpu/raster_options.py --data ROOM0 --format replica --out DIR
    python bench/gpu/raster_options.py --device cpu --gaussians 2000 --width 64 --height 48   # smoke run

Writes ``raster-options.json`` and ``raster-options.md`` into ``--out`` (default ``$RESULTS/raster-options``
where ``RESULTS`` is set) and prints the table. Where gsplat cannot render (the CPU), the gsplat-only sets
are skipped with the reason and the others run on that backend.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import ogmapping  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its thread pool)

# isort: split
import torch

from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.frames.frame import Frame
from ogmapping.frames.geometry import backproject, intrinsics_matrix, valid_depth, world_to_camera
from ogmapping.frames.preprocess import prepare, resize_frame
from ogmapping.optim.refine import gradient_norms
from ogmapping.optim.selective_adam import SelectiveAdam
from ogmapping.quality.evaluation import open_frames
from ogmapping.quality.metrics import psnr
from ogmapping.render import Camera, RasterOptions, RenderOutput, SplatSet, rasterize_batch, resolve_backend
from ogmapping.render.gsplat_backend import unavailable_reason
from ogmapping.render.options import DEFAULT
from ogmapping.runtime.machine import machine
from ogmapping.runtime.profile import resolve_device

FRAME_GAP = 10  # the views: frames 0, 10, 20, ...
VIEWS_A_STEP = 2
SYNTHETIC_FRAMES = 100  # the synthetic room's sequence: its orbit turns 280 degrees over them
DEPTH_RANGE = (0.1, 5.0)  # octree.depth_min, octree.depth_max (their defaults)
GROWTH_THRESHOLD = 2e-4  # refine.grad_threshold's default, NDC units
DEPTH_WEIGHT = 0.5  # loss.depth's default
# 3DGS's learning rates (its means' rate for a scene of a few metres)
LEARNING_RATES = {"means": 1.6e-4, "quats": 1e-3, "log_scales": 5e-3, "opacity_logits": 5e-2, "colours": 2.5e-3}


@dataclass(frozen=True)
class OptionSet:
    name: str
    what: str
    raster: RasterOptions = DEFAULT
    selective: bool = False


OPTION_SETS = (
    OptionSet("baseline", "today's step: unpacked, classic projection, torch's Adam (fused on CUDA)"),
    OptionSet("packed", "render.packed: gsplat's packed layout, one call a view", RasterOptions(packed=True)),
    OptionSet("absgrad", "render.absgrad: growth reads the summed absolute gradient", RasterOptions(absgrad=True)),
    OptionSet("antialiased", "render.antialiased: opacity compensation (Mip-Splatting)",
              RasterOptions(antialiased=True)),
    OptionSet("selective", "optim.selective: Adam steps only the Gaussians seen", selective=True),
)


@dataclass
class Scene:
    """The two views (cameras, target colour and depth on the device) and the Gaussians' starting values."""

    cameras: list[Camera]
    targets: list[tuple[torch.Tensor, torch.Tensor]]
    start: dict[str, torch.Tensor]
    source: str

    @property
    def size(self) -> tuple[int, int]:
        return self.cameras[0].size


def load_frames(args: argparse.Namespace) -> tuple[list[Frame], list[Frame], str]:
    """The views (``--views`` frames ``FRAME_GAP`` apart from frame 0, at ``--width``; as many as the sequence
    holds, at least two) and the map's frames (``--map-frames`` spread over the sequence, at ``--map-scale``
    of that width), depth on the colour grid and clipped as the mapper has them. ``--data`` keeps its
    aspect; the synthetic room is rendered at ``--width`` x ``--height``."""
    if args.data is None:
        size = (args.width, args.height)
        full = SyntheticSource(n_frames=SYNTHETIC_FRAMES, width=size[0], height=size[1])
        small = SyntheticSource(n_frames=SYNTHETIC_FRAMES, width=round(size[0] * args.map_scale),
                                height=round(size[1] * args.map_scale))
        count, described = SYNTHETIC_FRAMES, "the synthetic room"
        view, mapped = full.__getitem__, small.__getitem__
    else:
        opened = open_frames(args.data, args.format)
        count, described = len(opened.source), f"{args.data} ({args.format})"

        def sized(position: int, width: float) -> Frame:
            frame = opened.load(position)
            scale = width / frame.color_intrinsics.width
            return frame if scale == 1.0 else resize_frame(frame, scale)

        view = lambda position: sized(position, args.width)  # noqa: E731
        mapped = lambda position: sized(position, args.width * args.map_scale)  # noqa: E731
    if count <= FRAME_GAP:
        raise ValueError(f"the views are frames 0, {FRAME_GAP}, ...; {described} holds {count} frames")
    viewed = list(range(0, min(count, args.views * FRAME_GAP), FRAME_GAP))
    positions = sorted({round(i * (count - 1) / max(args.map_frames - 1, 1)) for i in range(args.map_frames)})
    views = [prepare(view(position), *DEPTH_RANGE) for position in viewed]
    map_frames = [prepare(mapped(position), *DEPTH_RANGE) for position in positions]
    return views, map_frames, (f"{described}: views frames {', '.join(map(str, viewed))}, the map from frames "
                               f"{', '.join(map(str, positions))} at {args.map_scale:g} of the views' width")


def starting_gaussians(frames: list[Frame], count: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
    """``count`` of the frames' depth pixels, back-projected: each Gaussian as wide as the pixels it stands
    for, its colour the pixel's; colour and scale then perturbed and opacity set to 0.73."""
    points, colours, footprints = [], [], []
    for frame in frames:
        depth = torch.as_tensor(frame.depth)
        valid = valid_depth(depth)
        points.append(backproject(depth, frame.color_intrinsics, torch.as_tensor(frame.c2w, dtype=torch.float32)))
        colours.append(torch.as_tensor(frame.rgb)[valid])
        footprints.append(depth[valid] / frame.color_intrinsics.fx)  # metres a pixel spans at that depth
    available = sum(len(part) for part in points)
    if count > available:
        raise ValueError(f"--gaussians {count}: these frames hold {available} depth pixels, at most that many")
    chosen = torch.randperm(available, generator=generator)[:count]
    scales = torch.cat(footprints)[chosen] * math.sqrt(available / count)
    noise = lambda *shape: torch.randn(*shape, generator=generator)  # noqa: E731
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(count, 4)
    return {
        "means": torch.cat(points)[chosen],
        "quats": identity + 0.05 * noise(count, 4),
        "log_scales": scales.log().unsqueeze(-1).expand(count, 3) + 0.2 * noise(count, 3),
        "opacity_logits": torch.ones(count),
        "colours": (torch.cat(colours)[chosen] + 0.1 * noise(count, 3)).clamp(0.0, 1.0),
    }


def build_scene(args: argparse.Namespace, device: torch.device) -> Scene:
    frames, map_frames, source = load_frames(args)
    generator = torch.Generator().manual_seed(args.seed)
    start = {name: value.to(device).contiguous() for name, value in
             starting_gaussians(map_frames, args.gaussians, generator).items()}
    cameras = [Camera(world_to_camera(torch.as_tensor(frame.c2w, dtype=torch.float32)).to(device),
                      intrinsics_matrix(frame.color_intrinsics, device), frame.color_intrinsics.width,
                      frame.color_intrinsics.height) for frame in frames]
    targets = [(torch.as_tensor(frame.rgb, device=device), torch.as_tensor(frame.depth, device=device))
               for frame in frames]
    return Scene(cameras, targets, start, source)


def splats(params: dict[str, torch.Tensor]) -> SplatSet:
    return SplatSet(params["means"], params["quats"], params["log_scales"].exp(),
                    torch.sigmoid(params["opacity_logits"]), params["colours"])


def render(params: dict[str, torch.Tensor], scene: Scene, backend: str, options: RasterOptions,
           views: list[int]) -> list[RenderOutput]:
    """The Gaussians seen from ``scene``'s views ``views``, in one batch."""
    gaussians = splats(params)
    return rasterize_batch([gaussians] * len(views), [scene.cameras[view] for view in views], backend=backend,
                           options=options)


def step_views(step: int, count: int) -> list[int]:
    """The views step ``step`` renders: ``VIEWS_A_STEP`` neighbours of ``count``, one further each step, as the
    engine's window changes from step to step (rows seen in one step and not the next keep Adam's momentum)."""
    return [(step + offset) % count for offset in range(VIEWS_A_STEP)]


def loss_of(outputs: list[RenderOutput], scene: Scene, views: list[int]) -> torch.Tensor:
    """Colour L1 and depth L1 (where the frame has depth) of the views, as the mapping loss's L1 terms."""
    total = torch.zeros((), device=outputs[0].color.device)
    for output, (rgb, depth) in zip(outputs, [scene.targets[view] for view in views], strict=True):
        depth_error = torch.where(depth > 0, (output.depth - depth).abs(), 0.0)
        total = total + (output.color - rgb).abs().mean() + DEPTH_WEIGHT * depth_error.mean()
    return total


class Clock:
    """Each timed step's milliseconds: CUDA events on a GPU (read once, at the end), else the host's clock."""

    def __init__(self, device: torch.device) -> None:
        self.cuda = device.type == "cuda"
        self.marks: list[Any] = []

    def mark(self) -> None:
        if self.cuda:
            event = torch.cuda.Event(enable_timing=True)
            event.record()
            self.marks.append(event)
        else:
            self.marks.append(time.perf_counter())

    def milliseconds(self) -> list[float]:
        starts, ends = self.marks[0::2], self.marks[1::2]
        if self.cuda:
            torch.cuda.synchronize()
            return [start.elapsed_time(end) for start, end in zip(starts, ends, strict=True)]
        return [1e3 * (end - start) for start, end in zip(starts, ends, strict=True)]


def run(option: OptionSet, scene: Scene, backend: str, args: argparse.Namespace,
        device: torch.device) -> tuple[dict[str, Any], list[torch.Tensor]]:
    """The set's figures, and its final render's colour per view (PSNRs over every view's pixels together)."""
    params = {name: value.clone().requires_grad_(True) for name, value in scene.start.items()}
    groups = [{"params": [param], "lr": LEARNING_RATES[name], "name": name} for name, param in params.items()]
    fused = device.type == "cuda" or None  # as the engine's static-shape step on CUDA
    optimizer = (SelectiveAdam(groups, row_groups=params, eps=1e-15, fused=fused) if option.selective
                 else torch.optim.Adam(groups, eps=1e-15, fused=fused))
    width, height = scene.size
    count = args.gaussians
    sums = {"plain": torch.zeros(count, device=device), "absolute": torch.zeros(count, device=device)}
    observed, drawn = torch.zeros(count, device=device), torch.zeros((), device=device)
    clock = Clock(device)
    if device.type == "cuda":
        torch.cuda.synchronize()
        torch.cuda.reset_peak_memory_stats(device)
    for index in range(args.warmup + args.steps):
        timed = index >= args.warmup
        if timed:
            clock.mark()
        optimizer.zero_grad(set_to_none=True)
        views = step_views(index, len(scene.cameras))
        outputs = render(params, scene, backend, option.raster, views)
        loss_of(outputs, scene, views).backward()
        if option.selective:
            optimizer.select(torch.stack([output.visible for output in outputs]).any(dim=0))
        optimizer.step()
        if timed:
            clock.mark()
            for output in outputs:  # outside the timed span: growth's statistics over the timed steps
                sums["plain"] += gradient_norms(output.screen_gradient(), output.visible, width, height)
                if option.raster.absgrad:
                    sums["absolute"] += gradient_norms(output.screen_gradient(absolute=True), output.visible,
                                                       width, height)
                observed += output.visible
                drawn += output.visible.sum()
    times = clock.milliseconds()
    with torch.no_grad():
        # copies: a backend may reuse its output buffers in the next set's renders
        final = [output.color.clone() for output in render(params, scene, backend, option.raster,
                                                           list(range(len(scene.cameras))))]

    def share(sums: torch.Tensor) -> float:
        seen = observed > 0
        mean = sums / observed.clamp_min(1)
        return float(((mean >= GROWTH_THRESHOLD) & seen).sum() / seen.sum().clamp_min(1))

    figures = {
        "step_ms_median": statistics.median(times),
        "step_ms_fastest": min(times),
        "peak_gpu_mb": torch.cuda.max_memory_allocated(device) / 1e6 if device.type == "cuda" else None,
        "drawn_per_view": float(drawn) / (args.steps * VIEWS_A_STEP),
        "psnr_vs_frames_db": psnr(torch.stack(final), torch.stack([rgb for rgb, _ in scene.targets])),
        "growth_share": share(sums["absolute"] if option.raster.absgrad else sums["plain"]),
        "growth_share_plain_gradient": share(sums["plain"]),
    }
    return figures, final


def skip_reason(option: OptionSet, backend: str) -> str | None:
    """Why ``option`` does not run here: gsplat's options where another backend renders."""
    if backend == "gsplat" or option.raster == DEFAULT:
        return None
    why = unavailable_reason()
    return f"gsplat's option; this run renders with the {backend} backend" + (f" ({why})" if why else "")


def measure(args: argparse.Namespace) -> dict[str, Any]:
    started = time.perf_counter()
    device = resolve_device(args.device)
    backend = resolve_backend(args.backend, device)
    scene = build_scene(args, device)
    results, baseline = [], None
    for option in (option for option in OPTION_SETS if option.name in args.sets):
        entry: dict[str, Any] = {"name": option.name, "what": option.what, "skipped": skip_reason(option, backend)}
        if entry["skipped"] is not None:
            print(f"{option.name}: skipped: {entry['skipped']}", file=sys.stderr)
        else:
            figures, final = run(option, scene, backend, args, device)
            baseline = final if option.name == "baseline" else baseline
            entry.update(figures)
            entry["psnr_vs_baseline_db"] = (None if baseline is None or option.name == "baseline" else
                                            psnr(torch.stack(final), torch.stack(baseline)))
        results.append(entry)
    width, height = scene.size
    return {
        "device": str(device), "backend": backend, "machine": machine(device).to_dict(), "source": scene.source,
        "width": width, "height": height, "gaussians": args.gaussians, "views": len(scene.cameras),
        "views_a_step": VIEWS_A_STEP,
        "warmup": args.warmup, "steps": args.steps, "growth_threshold": GROWTH_THRESHOLD, "options": results,
        "seconds": time.perf_counter() - started,
    }


def number(value: float | None, digits: int) -> str:
    if value is None:
        return "–"
    return "inf" if math.isinf(value) else f"{value:.{digits}f}"


def table(report: dict[str, Any]) -> str:
    lines = [
        f"Raster options: {report['gaussians']} Gaussians, {report['views_a_step']} of {report['views']} views a "
        f"step at {report['width']}x{report['height']}, from {report['source']}; {report['device']}, backend "
        f"{report['backend']}; median of {report['steps']} steps after {report['warmup']} "
        f"({report['seconds']:.0f} s in all). PSNR over every view's final render; growth share: drawn Gaussians "
        f"whose mean screen-space gradient reaches {report['growth_threshold']:g} (NDC), as growth reads it.",
        "",
        "| set | what | step ms (median / fastest) | peak GPU MB | drawn per view | PSNR vs baseline dB "
        "| PSNR vs frames dB | growth share (plain gradient) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for entry in report["options"]:
        if entry["skipped"] is not None:
            lines.append(f"| {entry['name']} | {entry['what']} | skipped: {entry['skipped']} | | | | | |")
            continue
        lines.append(
            f"| {entry['name']} | {entry['what']} | {number(entry['step_ms_median'], 2)} / "
            f"{number(entry['step_ms_fastest'], 2)} | {number(entry['peak_gpu_mb'], 0)} | "
            f"{entry['drawn_per_view']:.0f} | {number(entry['psnr_vs_baseline_db'], 2)} | "
            f"{number(entry['psnr_vs_frames_db'], 2)} | {entry['growth_share']:.3f} "
            f"({entry['growth_share_plain_gradient']:.3f}) |")
    return "\n".join([*lines, "", f"- machine: {json.dumps(report['machine'])}"])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda", help="auto, cpu, cuda or cuda:N (default %(default)s)")
    parser.add_argument("--backend", default="auto", help="rasterizer backend (default %(default)s)")
    parser.add_argument("--gaussians", type=int, default=3_000_000, help="Gaussians in all (default %(default)s)")
    parser.add_argument("--width", type=int, default=1200)
    parser.add_argument("--height", type=int, default=680, help="the synthetic room's only; data keeps its aspect")
    parser.add_argument("--data", help="a dataset folder (default: the synthetic room)")
    parser.add_argument("--format", default="auto", help="its format (default %(default)s)")
    parser.add_argument("--steps", type=int, default=20, help="timed steps per set (default %(default)s)")
    parser.add_argument("--warmup", type=int, default=5, help="untimed steps first (default %(default)s)")
    parser.add_argument("--views", type=int, default=4, help="views, frames 0, 10, ..., two a step, one further "
                        "each step (default %(default)s)")
    parser.add_argument("--map-frames", type=int, default=20, help="frames the map is made from, spread over the "
                        "sequence (default %(default)s)")
    parser.add_argument("--map-scale", type=float, default=0.5, help="their size, of the views' (default %(default)s)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--sets", nargs="+", default=[option.name for option in OPTION_SETS],
                        choices=[option.name for option in OPTION_SETS], help="option sets (default: all)")
    parser.add_argument("--out", type=Path, default=Path(os.environ["RESULTS"]) / "raster-options"
                        if os.environ.get("RESULTS") else None, help="folder for the JSON and the table")
    args = parser.parse_args(argv)
    if min(args.steps, args.gaussians, args.map_frames, args.views - 1) < 1 or args.warmup < 0 \
            or not 0 < args.map_scale <= 1:
        parser.error("--steps, --gaussians and --map-frames must be positive, --views at least 2, --warmup not "
                     "negative, --map-scale in (0, 1]")
    report = measure(args)
    markdown = table(report)
    print(markdown)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "raster-options.json").write_text(json.dumps(report, indent=2) + "\n")
        (args.out / "raster-options.md").write_text(markdown + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
