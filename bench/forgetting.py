"""Held-out PSNR per stretch of the sequence at the end of a run: how much of early regions the map forgets.

Maps the streamed frames once per setting (frames decoded before the clock starts), then scores
every held-out frame (index % 10 == 5) and prints the mean per stretch of ``--stretch`` frames,
oldest first. Comparing a run over a short prefix with a run over the whole sequence shows what
the later frames cost the early ones.

    .venv/bin/python bench/forgetting.py --frames 0:300 --scale 0.25 "" "keyframes.global_count=2"
"""

from __future__ import annotations

import argparse

import ogmapping  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its thread pool)

# isort: split
import numpy as np
from sequence import add_sequence_arguments, load_sequence, map_setting

from ogmapping.quality.evaluation import ground_truth, score


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("settings", nargs="+", help='space-separated KEY=VALUE overrides per setting ("" = preset)')
    add_sequence_arguments(parser)
    parser.add_argument("--stretch", type=int, default=60, help="frames per stretch in the summary (default 60)")
    args = parser.parse_args()
    sequence = load_sequence(args)
    selection = sequence.selection
    for setting in args.settings:
        run = map_setting(args.preset, setting, sequence.streamed)
        mapper = run.mapper
        truths = [ground_truth(frame, run.config) for frame in sequence.heldout]
        psnr = np.array([score(mapper.render(t.c2w, t.color_intrinsics), t)["psnr"] for t in truths])
        first = selection.heldout[0]
        stretches = {}
        for index, value in zip(selection.heldout, psnr, strict=True):
            stretches.setdefault((index - first) // args.stretch, []).append(value)
        summary = " ".join(f"{np.mean(values):.2f}" for _, values in sorted(stretches.items()))
        print(f"{args.preset} [{setting}]: {run.fps(len(sequence.streamed)):.2f} FPS, "
              f"{mapper.model.iterations} iterations, "
              f"{len(mapper.model.anchors)} anchors; held-out PSNR {psnr.mean():.2f} dB; "
              f"per {args.stretch} frames: {summary}", flush=True)


if __name__ == "__main__":
    main()
