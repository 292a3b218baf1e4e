"""Operators, and the ones a GPU would wait on, per optimisation step of ``Mapper.process`` on real frames.

Counts every operator dispatched below autograd while the mapper processes the frames after ``--warm``
warm ones, and the host-waiting ones among them (``nonzero``, ``item``, ``unique``, boolean-mask indexing,
``masked_select``, ``repeat_interleave`` without an output size, as ``tests/test_host_waits.py`` counts
them), then spreads them over the steps those frames took: per-frame work included, seen from outside the
engine.

    .venv/bin/python bench/host_waits.py --data ../shared/data/7scenes-redkitchen --frames 0:30 --scale 0.5
    .venv/bin/python bench/host_waits.py --data ../shared/data/7scenes-redkitchen --frames 0:30 --step static
"""

from __future__ import annotations

import argparse
import json
from collections import Counter

import ogmapping  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its thread pool)

# isort: split
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from ogmapping.config import PRESETS, resolve
from ogmapping.mapper import Mapper
from ogmapping.quality.evaluation import open_frames

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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="dataset folder")
    parser.add_argument("--format", default="auto")
    parser.add_argument("--frames", default="0:30", help="START:END (default 0:30)")
    parser.add_argument("--scale", type=float, default=0.5, help="image scale (default 0.5)")
    parser.add_argument("--preset", default="sparse", choices=PRESETS)
    parser.add_argument("--warm", type=int, default=10, help="frames mapped before counting (default 10)")
    parser.add_argument("--step", default="dynamic", choices=["dynamic", "static"],
                        help="config step (default dynamic, the CPU's; compiled graphs run eagerly under the count, "
                        "so static counts what they run)")
    args = parser.parse_args()
    frames = open_frames(args.data, args.format, args.frames, 1, args.scale)
    mapper = Mapper(resolve(args.preset, overrides={"step": args.step}), "cpu")
    streamed = frames.selection.streamed
    for position in streamed[:args.warm]:
        mapper.process(frames.load(position))
    count, steps = Count(), 0
    for position in streamed[args.warm:]:
        frame = frames.load(position)
        with count:
            steps += mapper.process(frame).iterations
    print(json.dumps({"frames": len(streamed) - args.warm, "steps": steps,
                      "operators_per_step": round(count.operators / steps, 1),
                      "host_waits_per_step": round(sum(count.waits.values()) / steps, 1),
                      "host_waits": dict(count.waits.most_common())}, indent=2))


if __name__ == "__main__":
    main()
