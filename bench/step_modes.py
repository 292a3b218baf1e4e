"""One steady mapping step's time in each step mode (config ``step``), on the test suite's map.

The map is ``tests/steady_step.py``'s: the synthetic room after four frames, the next frame as the view
and the two newest keyframes as its window (three views a step), growth and pruning off. Each mode gets
its own map, a few uncounted steps (the compiled mode compiles then), then ``--steps`` timed steps; the
median and the fastest are printed.

    python bench/step_modes.py                      # sparse: dynamic, static, compiled
    python bench/step_modes.py --preset dense --modes dynamic static
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import ogmapping  # noqa: F401  (before torch: the thread-pool settings)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from steady_step import mapped

from ogmapping.runtime.threads import torch_threads

WARM_STEPS = 3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", default="sparse", help="config preset (default %(default)s)")
    parser.add_argument("--modes", nargs="+", default=["dynamic", "static", "compiled"],
                        choices=["dynamic", "static", "compiled"], help="step modes to time (default: all three)")
    parser.add_argument("--steps", type=int, default=20, help="timed steps per mode (default %(default)s)")
    args = parser.parse_args()
    for mode in args.modes:
        mapper, view, window = mapped(args.preset, {"refine.interval": "10000"}, step=mode)
        with torch_threads(mapper.profile.threads):
            for _ in range(WARM_STEPS):
                mapper.steps.step(view, window)
            times = []
            for _ in range(args.steps):
                start = time.perf_counter()
                mapper.steps.step(view, window)
                times.append(time.perf_counter() - start)
        print(f"{args.preset} step={mode}: median {1e3 * statistics.median(times):.1f} ms, "
              f"fastest {1e3 * min(times):.1f} ms over {args.steps} steps ({len(mapper.model.anchors)} anchors, "
              f"buffers of {mapper.model.anchors.capacity} rows)")


if __name__ == "__main__":
    main()
