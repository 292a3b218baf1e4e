"""``ogmap run``: stream a dataset through the mapper, then score it on streamed and held-out views.

The mapper takes the data's poses, or a trajectory file's (``--poses``), and views are judged at the poses
it was given; with ``--eval-poses`` they are judged a second time at a trajectory file's (the exact one),
so a map made from noisy poses is also scored against the truth.
"""

from __future__ import annotations

import dataclasses
import json
import resource
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import torch
from tqdm import tqdm

from ogmapping.cli.pose_log import PoseLog
from ogmapping.cli.trajectory import check_covers
from ogmapping.config import MapperConfig
from ogmapping.frames.trajectory import read_tum
from ogmapping.mapper import Mapper
from ogmapping.quality.evaluation import evaluate_views, mapper_render, open_frames
from ogmapping.runtime.machine import machine
from ogmapping.runtime.profile import resolve_device
from ogmapping.warmup import warm_up

MEMORY_LOG_INTERVAL = 100  # streamed frames between peak-memory records
# With poses.refine: the streamed frames' refined poses, keyframes' as they ended (where only keyframes are refined,
# every other frame's moved as its nearest keyframe's, as renders of its time are).
REFINED_POSES = "refined.tum"
EVAL_POSES_KEY = "at_eval_poses"  # results.json's scores at --eval-poses, and their previews' name prefix
STEP_STAGES = ("window", "decode", "rasterize", "loss", "backward", "statistics", "optimizer", "refine")


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
    poses: Path | None = None  # TUM file to map with instead of the data's poses
    eval_poses: Path | None = None  # TUM file to judge every view at as well


def step_seconds(timings: dict[str, float]) -> float:
    """Time spent in optimisation steps: the stages of ``Mapper._iteration`` and refinement (decode and
    rasterize also count the few renders allocation makes, a small share)."""
    return sum(seconds for stage, seconds in timings.items() if stage in STEP_STAGES)


def memory_snapshot(frames: int, anchors: int, device: torch.device) -> dict:
    """Peak memory so far, so a run can show it stays flat once the scene stops growing."""
    return {
        "frames": frames,
        "anchors": anchors,
        "peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        "peak_gpu_memory_bytes": torch.cuda.max_memory_allocated(device) if device.type == "cuda" else None,
    }


T = TypeVar("T")


def prefetched(load: Callable[[int], T], positions: Iterable[int], depth: int = 4) -> Iterator[T]:
    """``load`` of each position in order, run ``depth`` ahead on a background thread (image decoding and
    numpy's array work release the GIL)."""
    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="prefetch") as pool:
        pending: deque[Future[T]] = deque()
        for position in positions:
            pending.append(pool.submit(load, position))
            if len(pending) > depth:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


def run(options: RunOptions, config: MapperConfig) -> dict:
    """Map, evaluate and write results.json, previews and the snapshot into ``options.out``."""
    device = resolve_device(options.device)
    frames = open_frames(options.data, options.format, options.frames, options.stride, options.scale,
                         **options.dataset_options)
    selection = frames.selection
    for line in frames.source.report():
        print(f"{frames.source.name}: {line}", flush=True)
    mapped_poses = read_tum(options.poses) if options.poses is not None else None
    eval_poses = read_tum(options.eval_poses) if options.eval_poses is not None else None
    check_covers(frames, [t for t in (mapped_poses, eval_poses) if t is not None], options.progress)
    frames = dataclasses.replace(frames, poses=mapped_poses)
    out = Path(options.out)
    out.mkdir(parents=True, exist_ok=True)
    warm_up_seconds = warm_up(device, config.backend, config.step)  # kernel loads, CUDA, graphs: not mapping time
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    mapper = Mapper(config, device)

    keyframes = 0
    pose_log = PoseLog() if config.poses.refine else None
    start = time.perf_counter()
    memory_log = []
    progress = tqdm(total=len(selection.streamed), desc="mapping", unit="frame", disable=not options.progress)
    # Frames are read and prepared (``Mapper.prepare``) on the prefetch thread while the previous ones map.
    for count, prepared in enumerate(prefetched(lambda position: mapper.prepare(frames.load(position)),
                                                selection.streamed), start=1):
        result = mapper.process(prepared)
        keyframes += result.keyframe
        if pose_log is not None:
            pose_log.add(prepared.given, result)
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
    render = mapper_render(mapper)
    evaluation = evaluate_views(frames, config, render, out, options.progress, device)
    at_eval_poses: dict[str, dict] = {}
    if eval_poses is not None:
        judged = evaluate_views(frames, config, render, out, options.progress, device, eval_poses.pose_of,
                                f"{EVAL_POSES_KEY}_")
        at_eval_poses = {EVAL_POSES_KEY: {**judged.splits, "poses": eval_poses.name}}

    refinement: dict[str, dict] = {}
    if pose_log is not None:
        settings = mapper.config.poses
        pose_log.settle(mapper.keyframe_poses(), follow_nearest=not (settings.track_iterations or settings.view_steps))
        pose_log.write(out / REFINED_POSES)
        refinement = {"pose_refinement": {**pose_log.summary(eval_poses), "trajectory": REFINED_POSES}}
    stats = mapper.stats()
    sample = frames.load(selection.streamed[0])
    results = {
        **evaluation.splits,
        **at_eval_poses,
        **refinement,
        "poses": mapped_poses.name if mapped_poses is not None else None,
        "processing_fps": len(selection.streamed) / mapping_seconds,
        "mapping_seconds": mapping_seconds,
        "warm_up_seconds": warm_up_seconds,
        "render_fps": evaluation.render_fps,
        "snapshot_bytes": len(snapshot),
        "anchors": stats.anchors,
        "anchors_per_level": stats.anchors_per_level,
        "gaussians": stats.gaussians,
        "keyframes": stats.keyframes,
        "iterations": stats.iterations,
        "steps_per_frame": stats.iterations / len(selection.streamed),
        "seconds_per_step": step_seconds(stats.timings) / stats.iterations if stats.iterations else None,
        "time_per_stage_seconds": stats.timings,
        "peak_rss_bytes": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
        "peak_gpu_memory_bytes": torch.cuda.max_memory_allocated(device) if device.type == "cuda" else None,
        "memory_per_100_frames": memory_log,
        "device": str(device),
        "machine": machine(device).to_dict(),
        "backend": stats.backend,
        "step": mapper.profile.step_mode,
        "preset": options.preset,
        "resolution": [sample.color_intrinsics.width, sample.color_intrinsics.height],
        "frames": {"streamed": len(selection.streamed), "heldout": len(selection.heldout),
                   "range": options.frames, "stride": options.stride, "scale": options.scale},
        "lpips": evaluation.lpips,
        "source": {"name": frames.source.name, "report": frames.source.report()},
        "config": config.to_dict(),
    }
    (out / "results.json").write_text(json.dumps(results, indent=2))
    return results
