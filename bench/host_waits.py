"""Operators, and the ones a GPU would wait on, per optimisation step of ``Mapper.process`` on real frames.

Counts every operator dispatched below autograd while the mapper processes the frames after ``--warm``
warm ones, and the host-waiting ones among them (``nonzero``, ``item``, ``unique``, boolean-mask indexing,
``masked_select``, ``repeat_interleave`` without an output size, as ``tests/test_host_waits.py`` counts
them) plus the engine's own reads of device values (``ogmapping.runtime.host_read``, which no operator
shows), then spreads them over the steps those frames took: per-frame work included, seen from outside
the engine.

    .venv/bin/python bench/host_waits.py --data ../shared/data/7scenes-redkitchen --frames 0:30 --scale 0.5
    .venv/bin/python bench/host_waits.py --data ../shared/data/7scenes-redkitchen --frames 0:30 --step static
    .venv/bin/python bench/host_waits.py --data ../shared/data/7scenes-redkitchen --frames 0:30 --step static --profiler

``--profiler`` counts with torch's profiler instead, so the compiled graphs run compiled: each operator
called outside a graph, each fused kernel and each rasterizer stage once, as ``tests/test_dispatch_budget.py``
counts a compiled step.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager

import ogmapping  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its thread pool)

# isort: split
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from ogmapping.config import PRESETS, resolve
from ogmapping.mapper import Mapper
from ogmapping.quality.evaluation import open_frames
from ogmapping.runtime.host_read import reads

WAITING = {"aten.nonzero.default", "aten._local_scalar_dense.default", "aten._unique2.default",
           "aten.unique_dim.default", "aten.unique_consecutive.default", "aten.masked_select.default",
           "aten.repeat_interleave.Tensor"}


class Count(TorchDispatchMode):
    """Every operator, and the host-waiting ones by name."""

    def __init__(self) -> None:
        super().__init__()
        self.operators = 0
        self.waits: Counter[str] = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.operators += 1
        name = str(func)
        indices = args[1] if len(args) > 1 and isinstance(args[1], (list, tuple)) else []
        if name in WAITING or (name.startswith("aten.index") and any(
                isinstance(index, torch.Tensor) and index.dtype == torch.bool for index in indices)):
            self.waits[name] += 1
        return func(*args, **(kwargs or {}))


@contextmanager
def profiled(count: Count) -> Iterator[None]:
    """Count into ``count`` with torch's profiler: outermost operators and Inductor's fused CPU kernels."""
    with torch._inductor.config.patch({"cpp.enable_kernel_profile": True}), \
            torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as profile:
        yield
    for event in profile.events():
        if _dispatched(event) and not any(_dispatched(outer) for outer in _enclosing(event)):
            count.operators += 1
            name = "aten." + event.name.removeprefix("aten::") + ".default"
            if name in WAITING or event.name == "aten::item":
                count.waits[event.name] += 1


def _dispatched(event) -> bool:
    return event.name.startswith(("aten::", "ogmapping::")) or "cpp_fused" in event.name


def _enclosing(event) -> Iterator:
    parent = event.cpu_parent
    while parent is not None:
        yield parent
        parent = parent.cpu_parent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="dataset folder")
    parser.add_argument("--format", default="auto")
    parser.add_argument("--frames", default="0:30", help="START:END (default 0:30)")
    parser.add_argument("--scale", type=float, default=0.5, help="image scale (default 0.5)")
    parser.add_argument("--preset", default="sparse", choices=PRESETS)
    parser.add_argument("--warm", type=int, default=10, help="frames mapped before counting (default 10)")
    parser.add_argument("--step", default="dynamic", choices=["dynamic", "static", "compiled"],
                        help="config step (default dynamic, the CPU's; static: static shapes, eager; compiled: static "
                        "shapes as graphs, which run eagerly under the default count: use --profiler)")
    parser.add_argument("--profiler", action="store_true",
                        help="count with torch's profiler: compiled graphs run compiled, a fused kernel counts once")
    args = parser.parse_args()
    frames = open_frames(args.data, args.format, args.frames, 1, args.scale)
    mapper = Mapper(resolve(args.preset, overrides={"step": args.step}), "cpu")
    streamed = frames.selection.streamed
    for position in streamed[:args.warm]:
        mapper.process(frames.load(position))
    count, steps, before = Count(), 0, reads()
    for position in streamed[args.warm:]:
        frame = frames.load(position)
        with profiled(count) if args.profiler else count:
            steps += mapper.process(frame).iterations
    count.waits["host_read.read"] = reads() - before
    print(json.dumps({"frames": len(streamed) - args.warm, "steps": steps,
                      "operators_per_step": round(count.operators / steps, 1),
                      "host_waits_per_step": round(sum(count.waits.values()) / steps, 1),
                      "host_waits": dict(count.waits.most_common())}, indent=2))


if __name__ == "__main__":
    main()
