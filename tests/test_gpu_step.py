"""One `sparse` mapping step at 640x480 on CUDA in steady state: host synchronisations and its time.

The map is built by streaming frames 0-39 (7-Scenes RedKitchen from ``$OGMAP_GPU_DATA`` or
../shared/data, else the synthetic scene) through ``Mapper.process``; a step is then one
optimisation iteration on the newest keyframe and a freshly drawn window, as a keyframe's steps are.

- ``torch.cuda.set_sync_debug_mode("warn")`` over a few steps: every synchronising call, by the
  engine's or gsplat's line that made it, goes to ``$OGMAP_GPU_REPORT/sync-sites.json``; a step (the
  default ``step=compiled``: static shapes, compiled graphs) may make at most one, gsplat's read of its
  tile-intersection count. The mode catches the implicit ones (a read of a device value, ``nonzero``),
  not an explicit ``torch.cuda.synchronize``; the stage timers make none while mapping (they record
  CUDA events and query them), which the profiler checks over a few steps.
- the stage timers' totals over a few steps: positive, and no more than the steps' time measured
  on the host around them with the device synchronised (nor much less: the stages cover the step).
- one step timed with CUDA events (and on the host), its kernel launches and synchronising runtime
  calls (explicit ones included) counted with torch's profiler: reported, not asserted, on the
  terminal and in ``$OGMAP_GPU_REPORT/step-time.json`` (``bench/gpu/check.sh`` sets both variables).
"""

from __future__ import annotations

import json
import os
import statistics
import time
import traceback
import warnings
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from test_gpu_gsplat import HAS_GSPLAT, fail_unless_usable

from ogmapping.config import resolve
from ogmapping.mapper import Mapper
from ogmapping.optim.keyframes import View
from ogmapping.quality.evaluation import open_frames
from ogmapping.runtime.streams import on_stream

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
    pytest.mark.skipif(not HAS_GSPLAT, reason="gsplat is not installed (see docs/cuda.md)"),
]
FRAMES = "0:40"
WARM_STEPS, TIMED_STEPS, CHECKED_STEPS = 5, 20, 5
RUNTIME_SYNCS = ("cudaDeviceSynchronize", "cudaStreamSynchronize", "cudaEventSynchronize")
EXPLICIT_SYNCS = ("cudaDeviceSynchronize", "cudaEventSynchronize")  # what a timer that waits would call


def report(name: str, text: str) -> None:
    folder = os.environ.get("OGMAP_GPU_REPORT")
    if folder:
        Path(folder).mkdir(parents=True, exist_ok=True)
        (Path(folder) / name).write_text(text)


@pytest.fixture(scope="module")
def steady(seven_scenes_if_present: Path | None) -> tuple[Mapper, View, str]:
    """A sparse map of frames 0-39 at 640x480 on CUDA, the newest keyframe as a view, and the data's name."""
    fail_unless_usable()
    data = os.environ.get("OGMAP_GPU_DATA") or seven_scenes_if_present
    if data is not None:
        frames = open_frames(str(data), "7scenes", FRAMES)
    else:
        frames = open_frames("synthetic", "synthetic", FRAMES, n_frames=40, width=640, height=480)
    mapper = Mapper(resolve("sparse"), "cuda")
    for position in frames.selection.streamed:
        mapper.process(frames.load(position))
    with on_stream(mapper.stream):  # the view is made where the mapper's steps will read it
        view = mapper.keyframes.keyframes[-1].view(mapper.device, compiled=mapper.profile.compiled)
    for _ in range(WARM_STEPS):  # window draws, downscaled copies and the allocator's cache settle
        step(mapper, view)
    torch.cuda.synchronize()
    return mapper, view, frames.source.name


def profiled(work: Callable[[], object]) -> tuple[list[str], dict[str, int]]:
    """The names of the events torch's profiler records over ``work``, and how often ``work`` calls
    each of ``RUNTIME_SYNCS``: less what an idle profile records, since the profiler's own exit
    synchronises the device once."""

    def events(run: Callable[[], object]) -> list[str]:
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU,
                                                torch.profiler.ProfilerActivity.CUDA]) as profile:
            run()
        return [event.name for event in profile.events()]

    idle, names = events(lambda: None), events(work)
    return names, {name: names.count(name) - idle.count(name) for name in RUNTIME_SYNCS}


def synchronising_sites(work: Callable[[], object]) -> Counter[str]:
    """Every synchronising call ``work`` makes (``set_sync_debug_mode("warn")``), by the engine's or gsplat's
    line that made it."""
    sites: Counter[str] = Counter()

    def record(message, category, filename, lineno, file=None, line=None) -> None:
        ours = [frame for frame in traceback.extract_stack()[:-1]
                if frame.filename != __file__ and ("ogmapping" in frame.filename or "gsplat" in frame.filename)]
        where = ours[-1] if ours else traceback.FrameSummary(filename, lineno, "?")
        sites[f"{where.filename.split('site-packages/')[-1].split('/ogmapping/')[-1]}:{where.lineno} {where.name}"] += 1

    torch.cuda.synchronize()
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.showwarning = record
        torch.cuda.set_sync_debug_mode("warn")
        try:
            work()
        finally:
            torch.cuda.set_sync_debug_mode("default")
    return sites


def step(mapper: Mapper, view: View) -> torch.Tensor:
    """One optimisation iteration on ``view`` (the newest keyframe) and a drawn window, as a keyframe's
    are, on the mapper's stream as ``process`` runs them."""
    with on_stream(mapper.stream):
        return mapper.steps.step(view, mapper.keyframes.draw_window(view_is_newest=True))


def test_step_time_and_launches_are_reported(steady: tuple[Mapper, View, str], capsys) -> None:
    mapper, view, source = steady
    device_ms, host_ms = [], []
    for _ in range(TIMED_STEPS):
        begin, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        tic = time.perf_counter()
        with on_stream(mapper.stream):
            begin.record()
            step(mapper, view)
            end.record()
        end.synchronize()
        host_ms.append((time.perf_counter() - tic) * 1e3)
        device_ms.append(begin.elapsed_time(end))
    names, syncs = profiled(lambda: step(mapper, view))
    figures = {
        "data": source,
        "gpu": torch.cuda.get_device_name(mapper.device),
        "torch": torch.__version__,
        "step": mapper.profile.step_mode,
        "window views": 1 + len(mapper.keyframes.draw_window(view_is_newest=True)),
        "anchors": len(mapper.model.anchors),
        "gaussians": mapper.model.last_gaussians,
        "steps timed": TIMED_STEPS,
        "step ms, CUDA events, median / min": [round(statistics.median(device_ms), 2), round(min(device_ms), 2)],
        "step ms, host, median / min": [round(statistics.median(host_ms), 2), round(min(host_ms), 2)],
        "kernel launches per step": sum("LaunchKernel" in name for name in names),
        "synchronising runtime calls per step": syncs,
    }
    text = json.dumps(figures, indent=2)
    report("step-time.json", text + "\n")
    with capsys.disabled():
        print(f"\none sparse step at {view.intrinsics.width}x{view.intrinsics.height} on CUDA:\n{text}")
    assert all(ms > 0 for ms in device_ms)


def test_a_steady_step_synchronises_at_most_at_gsplat_s_tile_count(steady: tuple[Mapper, View, str]) -> None:
    mapper, view, _ = steady
    sites = synchronising_sites(lambda: [step(mapper, view) for _ in range(CHECKED_STEPS)])
    per_step = {site: count / CHECKED_STEPS for site, count in sites.items()}
    report("sync-sites.json", json.dumps({"step": mapper.profile.step_mode, "per step": per_step}, indent=2) + "\n")
    assert sum(per_step.values()) <= 1 and all("gsplat" in site for site in per_step), per_step


def test_a_frame_synchronises_only_at_its_reads_and_gsplat_s(steady: tuple[Mapper, View, str],
                                                             seven_scenes_if_present: Path | None) -> None:
    """``Mapper.process`` of prepared frames: every synchronising call is one of the engine's counted reads
    (``host_read.read``: one a frame, one a keyframe insertion, one a refinement) or gsplat's tile count."""
    mapper, _, _ = steady
    data = os.environ.get("OGMAP_GPU_DATA") or seven_scenes_if_present
    frames = (open_frames(str(data), "7scenes", "40:48") if data is not None
              else open_frames("synthetic", "synthetic", "40:48", n_frames=48, width=640, height=480))
    prepared = [mapper.prepare(frames.load(position)) for position in frames.selection.streamed]
    steps = 0

    def process() -> None:
        nonlocal steps
        for frame in prepared:
            steps += mapper.process(frame).iterations

    sites = synchronising_sites(process)
    report("frame-sync-sites.json", json.dumps({"frames": len(prepared), "steps": steps, "sites": dict(sites)},
                                               indent=2) + "\n")
    assert all("host_read.py" in site or "gsplat" in site for site in sites), dict(sites)


def test_stage_timers_do_not_synchronise_while_mapping(steady: tuple[Mapper, View, str]) -> None:
    mapper, view, _ = steady
    mapper.timings  # noqa: B018 - read now, so that no pair is left pending from the steps before
    torch.cuda.synchronize()
    _, syncs = profiled(lambda: [step(mapper, view) for _ in range(CHECKED_STEPS)])
    assert {name: syncs[name] for name in EXPLICIT_SYNCS} == dict.fromkeys(EXPLICIT_SYNCS, 0)


def test_stage_totals_fit_the_synchronised_time_of_the_steps(steady: tuple[Mapper, View, str]) -> None:
    mapper, view, _ = steady
    before = mapper.timings
    torch.cuda.synchronize()
    tic = time.perf_counter()
    for _ in range(TIMED_STEPS):
        step(mapper, view)
    torch.cuda.synchronize()
    host = time.perf_counter() - tic
    after = mapper.timings
    staged = {name: seconds - before.get(name, 0.0) for name, seconds in after.items()}
    assert all(seconds >= 0 for seconds in staged.values()) and sum(staged.values()) > 0
    # A step's stages follow one another on the stream, so their device spans add up to no more
    # than the steps' time; what they leave out (zero_grad, the window's draw) is small.
    assert 0.25 * host <= sum(staged.values()) <= 1.05 * host + 1e-3, (staged, host)
