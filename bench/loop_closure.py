"""Loop closure on the synthetic room: a map made from drifting poses, then corrected, against exact poses.

The first ``--drift-frames`` mapped frames come with a pose drift that grows smoothly from nothing to
``--metres`` and ``--degrees`` (a turn about the world's up axis about the room's centre, and a shift), as
a SLAM system's odometry drifts before it closes a loop; the frames after them come with exact poses (the
SLAM has closed its loop). Three maps: ``exact`` (exact poses throughout), ``uncorrected`` (the drift kept)
and ``corrected`` (after the drifting frames, ``Mapper.correct_poses`` sends every keyframe's exact pose, as
``CorrectPoses`` would). Each is scored at its end on held-out frames (every 10th, not mapped) at their exact
poses: mean PSNR, and the gap to the exact map.

    .venv/bin/python bench/loop_closure.py --frames 60 --drift-frames 40 --width 160 --height 120
"""

from __future__ import annotations

import argparse
import time

import ogmapping  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its thread pool)

# isort: split
import numpy as np

from ogmapping.config import parse_override_args, resolve
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.frames.frame import Frame
from ogmapping.frames.rotation import axis_angle_matrix
from ogmapping.mapper import Mapper
from ogmapping.quality.metrics import psnr

MODES = ("exact", "uncorrected", "corrected")


def drifted(c2w: np.ndarray, fraction: float, metres: float, degrees: float) -> np.ndarray:
    """``c2w`` after a drift of ``fraction`` of the full one: turned about the world's z axis, then shifted."""
    motion = np.eye(4)
    motion[:3, :3] = axis_angle_matrix(np.array([0.0, 0.0, 1.0]), np.radians(degrees * fraction))
    motion[:3, 3] = np.array([1.0, 0.6, 0.0]) / np.linalg.norm([1.0, 0.6, 0.0]) * metres * fraction
    return motion @ c2w


def map_run(mode: str, frames: list[Frame], drift_frames: int, metres: float, degrees: float, config) -> Mapper:
    mapper = Mapper(config)
    exact = {frame.index: frame.c2w.copy() for frame in frames}
    for number, frame in enumerate(frames):
        if mode != "exact" and number < drift_frames:
            frame = Frame(frame.index, frame.rgb, frame.depth, frame.color_intrinsics, frame.depth_intrinsics,
                          drifted(frame.c2w, (number + 1) / drift_frames, metres, degrees), frame.timestamp)
        mapper.process(frame)
        if mode == "corrected" and number == drift_frames - 1:
            mapper.correct_poses({position: exact[keyframe.index]
                                  for position, keyframe in enumerate(mapper.keyframes.keyframes)})
    return mapper


def held_out_psnr(mapper: Mapper, held: list[Frame]) -> float:
    return float(np.mean([psnr(mapper.render(frame.c2w, frame.color_intrinsics).color, frame.rgb) for frame in held]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60, help="frames in the sequence (default 60)")
    parser.add_argument("--drift-frames", type=int, default=40, help="mapped frames that drift (default 40)")
    parser.add_argument("--metres", type=float, default=0.10, help="drift at its end (default 0.10)")
    parser.add_argument("--degrees", type=float, default=3.0, help="drift at its end (default 3)")
    parser.add_argument("--width", type=int, default=160)
    parser.add_argument("--height", type=int, default=120)
    parser.add_argument("--preset", default="sparse")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config overrides")
    args = parser.parse_args()
    source = SyntheticSource(n_frames=args.frames, width=args.width, height=args.height)
    loaded = [source[position] for position in range(len(source))]
    mapped = [frame for frame in loaded if frame.index % 10 != 5]
    held = [frame for frame in loaded if frame.index % 10 == 5]
    config = resolve(args.preset, overrides=parse_override_args(args.set))
    print(f"synthetic room, {len(mapped)} frames mapped ({args.drift_frames} drifting to {args.metres:g} m and "
          f"{args.degrees:g} degrees), {len(held)} held out, {args.width}x{args.height}, {args.preset}")
    scores = {}
    for mode in MODES:
        start = time.perf_counter()
        mapper = map_run(mode, mapped, args.drift_frames, args.metres, args.degrees, config)
        scores[mode] = held_out_psnr(mapper, held)
        print(f"{mode:12s} held-out PSNR at the exact poses {scores[mode]:6.2f} dB "
              f"(gap to exact {scores[mode] - scores['exact']:+.2f} dB), {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
