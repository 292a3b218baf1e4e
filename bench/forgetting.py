"""Held-out PSNR per stretch of the sequence at the end of a run: how much of early regions the map forgets.

Maps the streamed frames once per setting (frames decoded before the clock starts), then scores
every held-out frame (index % 10 == 5) and prints the mean per stretch of ``--stretch`` frames,
oldest first: the raw PSNR, and after it the PSNR once each frame's own affine colour map (gain and
offset) is fitted to its render (``psnr_affine``), which takes the frame's exposure out of the score.
Each held-out pose is rendered as a client pose of its frame's time (``mapper_render``: with
``poses.refine``, moved as the nearest keyframe was; then the raw PSNR at the poses as given follows).
Comparing a run over a short prefix with a run over the whole sequence shows what the later frames
cost the early ones; ``--at`` shows when: after each frame named there, the held-out frames before it
are scored as the map then stands (off the clock).

    .venv/bin/python bench/forgetting.py --frames 0:300 --scale 0.25 "" "keyframes.global_count=2"
    .venv/bin/python bench/forgetting.py --frames 0:600 --at 300,450 ""
"""

from __future__ import annotations

import argparse

import ogmapping  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its thread pool)

# isort: split
import numpy as np
from sequence import Sequence, add_sequence_arguments, load_sequence, map_setting

from ogmapping.frames.frame import Frame
from ogmapping.mapper import Mapper
from ogmapping.quality.evaluation import ground_truth, mapper_render, score
from ogmapping.quality.metrics import psnr


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("settings", nargs="+", help='space-separated KEY=VALUE overrides per setting ("" = preset)')
    add_sequence_arguments(parser)
    parser.add_argument("--stretch", type=int, default=60, help="frames per stretch in the summary (default 60)")
    parser.add_argument("--at", type=frame_indices, default=(),
                        help="comma-separated frame indices: once each is mapped (a held-out one: the next streamed "
                             "one), score the held-out frames before it as the map then stands (raw PSNR per stretch)")
    args = parser.parse_args()
    sequence = load_sequence(args)
    selection = sequence.selection
    streamed = selection.streamed
    if outside := [index for index in args.at if not streamed[0] <= index <= streamed[-1]]:
        parser.error(f"--at {outside[0]} is outside the streamed frames {streamed[0]}-{streamed[-1]}")
    for setting in args.settings:
        checkpoints = Checkpoints(args.at, sequence, args.stretch) if args.at else None
        run = map_setting(args.preset, setting, sequence.streamed, checkpoints)
        mapper = run.mapper
        truths = [ground_truth(frame, run.config) for frame in sequence.heldout]
        render = mapper_render(mapper)
        scores = [score(render(t.c2w, t.color_intrinsics, t), t) for t in truths]
        figures = [per_stretch([frame[key] for frame in scores], selection.heldout, args.stretch)
                   for key in ("psnr", "psnr_affine")]
        report = f"held-out PSNR raw {figures[0]}; PSNR affine-fit {figures[1]}"
        if run.config.poses.refine:  # the map has moved off the given poses: what a render at them sees
            given = [score(mapper.render(t.c2w, t.color_intrinsics), t)["psnr"] for t in truths]
            report += f"; raw at the poses as given, unmoved {per_stretch(given, selection.heldout, args.stretch)}"
        print(f"{args.preset} [{setting}]: {run.fps(len(sequence.streamed)):.2f} FPS, "
              f"{mapper.model.iterations} iterations, {len(mapper.model.anchors)} anchors; {report}", flush=True)


class Checkpoints:
    """``--at``: once the first streamed frame at or past a checkpoint is mapped (a held-out index names the next
    one), the held-out frames before it are scored as the map then stands."""

    def __init__(self, indices: tuple[int, ...], sequence: Sequence, stretch: int) -> None:
        self.pending = sorted(set(indices))
        self.sequence = sequence
        self.stretch = stretch
        self.truths: list[Frame] = []  # the held-out frames as the mapper sees them, prepared at the first checkpoint

    def __call__(self, frame: Frame, mapper: Mapper) -> None:
        if not self.pending or frame.index < self.pending[0]:
            return
        while self.pending and self.pending[0] <= frame.index:
            self.pending.pop(0)
        indices = [index for index in self.sequence.selection.heldout if index < frame.index]
        if not indices:
            return
        if not self.truths:
            self.truths = [ground_truth(truth, mapper.config) for truth in self.sequence.heldout]
        render = mapper_render(mapper)
        raw = [psnr(render(t.c2w, t.color_intrinsics, t).color, t.rgb) for t in self.truths[: len(indices)]]
        print(f"  after frame {frame.index}: held-out PSNR raw {per_stretch(raw, indices, self.stretch)}", flush=True)


def frame_indices(text: str) -> tuple[int, ...]:
    """``--at``'s comma-separated frame indices."""
    try:
        return tuple(int(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated frame indices, got {text!r}") from None


def per_stretch(values: list[float], indices: list[int], stretch: int) -> str:
    """The mean, then the mean of each ``stretch`` frames from the first index on."""
    stretches: dict[int, list[float]] = {}
    for index, value in zip(indices, values, strict=True):
        stretches.setdefault((index - indices[0]) // stretch, []).append(value)
    summary = " ".join(f"{np.mean(each):.2f}" for _, each in sorted(stretches.items()))
    return f"{np.mean(values):.2f} dB, per {stretch} frames: {summary}"


if __name__ == "__main__":
    main()
