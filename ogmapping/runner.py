"""``ogmap run``: stream a dataset through the mapper, then score it on streamed and held-out views."""

from __future__ import annotations

import json
import resource
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
from tqdm import tqdm

from ogmapping.config import MapperConfig
from ogmapping.datasets import open_dataset
from ogmapping.frame import Frame
from ogmapping.mapper import Mapper, Rendered
from ogmapping.metrics import Lpips, depth_l1_cm, psnr, ssim, summarise
from ogmapping.preprocess import prepare, resize_frame
from ogmapping.selection import select

PREVIEW_COUNT = 3
MEMORY_LOG_INTERVAL = 100  # streamed frames between peak-memory records


@dataclass
class RunOptions:
    data: str
    format: str = "auto"
    frames: str | None = None
    stride: int = 1
    scale: float = 1.0
    preset: str = "sparse"
    device: str = "auto"
    out: Path = Path("runs/latest")
    dataset_options: dict = field(default_factory=dict)
    progress: bool = True


def pick_device(name: str) -> torch.device:
    """``auto`` is CUDA when present, else the CPU; an explicit ``cuda`` without CUDA is an error."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda was asked for but this machine has no CUDA device")
    return device


def ground_truth(frame: Frame, config: MapperConfig) -> Frame:
    """The frame as the mapper sees it: depth on the colour grid, clipped to the working range."""
    return prepare(frame, config.octree.depth_min, config.octree.depth_max)


def score(rendered: Rendered, truth: Frame, lpips: Lpips | None = None) -> dict:
    """PSNR, SSIM, depth L1 and, with an available ``lpips``, LPIPS (None otherwise)."""
    return {
        "psnr": psnr(rendered.color, truth.rgb),
        "ssim": ssim(rendered.color, truth.rgb),
        "depth_l1_cm": depth_l1_cm(rendered.depth, truth.depth),
        "lpips": lpips(rendered.color, truth.rgb) if lpips is not None else None,
    }


def side_by_side(rendered: Rendered, truth: Frame) -> np.ndarray:
    """Render | ground truth on top, rendered depth | measured depth below, as a BGR uint8 image."""
    top = np.concatenate([rendered.color, truth.rgb], axis=1)
    far = max(float(np.percentile(truth.depth[truth.depth > 0], 99)) if (truth.depth > 0).any() else 1.0, 1e-3)
    depths = np.concatenate([rendered.depth, truth.depth], axis=1) / far
    bottom = cv2.applyColorMap((np.clip(depths, 0, 1) * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    top_bgr = cv2.cvtColor((np.clip(top, 0, 1) * 255).astype(np.uint8), cv2.COLOR_RGB2BGR)
    return np.concatenate([top_bgr, bottom], axis=0)


def memory_snapshot(frames: int, anchors: int, device: torch.device) -> dict:
    """Peak memory so far, so a run can show it stays flat once the scene stops growing."""
    return {
        "frames": frames,
        "anchors": anchors,
        "peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        "peak_gpu_memory_bytes": torch.cuda.max_memory_allocated(device) if device.type == "cuda" else None,
    }


def spread(items: list[int], count: int) -> list[int]:
    """Up to ``count`` items evenly spaced over the list, first and last included."""
    if len(items) <= count:
        return list(items)
    return [items[round(i * (len(items) - 1) / (count - 1))] for i in range(count)]


def prefetched(load: Callable[[int], Frame], positions: Iterable[int], depth: int = 4) -> Iterator[Frame]:
    """Frames in order, decoded by a background thread (image decoding releases the GIL)."""
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="prefetch") as pool:
        pending: deque[Future[Frame]] = deque()
        for position in positions:
            pending.append(pool.submit(load, position))
            if len(pending) > depth:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


def run(options: RunOptions, config: MapperConfig) -> dict:
    """Map, evaluate and write results.json, previews and the snapshot into ``options.out``."""
    device = pick_device(options.device)
    source = open_dataset(options.data, options.format, **options.dataset_options)
    selection = select(len(source), options.frames, options.stride)
    if not selection.streamed:
        raise ValueError("the frame selection leaves no frame to stream")
    out = Path(options.out)
    out.mkdir(parents=True, exist_ok=True)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    mapper = Mapper(config, device)

    def load(position: int) -> Frame:
        frame = source[position]
        return resize_frame(frame, options.scale) if options.scale != 1.0 else frame

    keyframes = 0
    start = time.perf_counter()
    memory_log = []
    progress = tqdm(total=len(selection.streamed), desc="mapping", unit="frame", disable=not options.progress)
    for count, frame in enumerate(prefetched(load, selection.streamed), start=1):
        result = mapper.process(frame)
        keyframes += result.keyframe
        progress.set_postfix(anchors=result.anchors, keyframes=keyframes, refresh=False)
        progress.update()
        if count % MEMORY_LOG_INTERVAL == 0:
            memory_log.append(memory_snapshot(count, result.anchors, device))
            if options.progress:
                tqdm.write(json.dumps(memory_log[-1]))
    progress.close()
    mapping_seconds = time.perf_counter() - start

    snapshot = mapper.snapshot()
    (out / "map.safetensors").write_bytes(snapshot)
    evaluation = {}
    render_seconds, renders = 0.0, 0
    previews = set(spread(selection.streamed, PREVIEW_COUNT)) | set(spread(selection.heldout, PREVIEW_COUNT))
    lpips = Lpips(device)
    for split, positions in (("streamed", selection.streamed), ("heldout", selection.heldout)):
        per_frame = []
        for position in tqdm(positions, desc=f"evaluating {split}", unit="frame", disable=not options.progress):
            truth = ground_truth(load(position), config)
            tic = time.perf_counter()
            rendered = mapper.render(truth.c2w, truth.color_intrinsics)
            render_seconds += time.perf_counter() - tic
            renders += 1
            per_frame.append(score(rendered, truth, lpips))
            if position in previews:
                cv2.imwrite(str(out / f"{split}_{position:06d}.png"), side_by_side(rendered, truth))
        evaluation[split] = summarise(per_frame)

    stats = mapper.stats()
    sample = load(selection.streamed[0])
    results = {
        **evaluation,
        "processing_fps": len(selection.streamed) / mapping_seconds,
        "mapping_seconds": mapping_seconds,
        "render_fps": renders / render_seconds if render_seconds > 0 else None,
        "snapshot_bytes": len(snapshot),
        "anchors": stats.anchors,
        "anchors_per_level": stats.anchors_per_level,
        "gaussians": stats.gaussians,
        "keyframes": stats.keyframes,
        "iterations": stats.iterations,
        "time_per_stage_seconds": stats.timings,
        "peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        "peak_gpu_memory_bytes": torch.cuda.max_memory_allocated(device) if device.type == "cuda" else None,
        "memory_per_100_frames": memory_log,
        "device": str(device),
        "backend": stats.backend,
        "preset": options.preset,
        "resolution": [sample.color_intrinsics.width, sample.color_intrinsics.height],
        "frames": {"streamed": len(selection.streamed), "heldout": len(selection.heldout),
                   "range": options.frames, "stride": options.stride, "scale": options.scale},
        "lpips": lpips.description,
        "config": config.to_dict(),
    }
    (out / "results.json").write_text(json.dumps(results, indent=2))
    return results
