"""Loop closure: a map made from drifting poses, then corrected, against one made from exact poses.

The first ``--drift-frames`` streamed frames come with a pose drift that grows smoothly from nothing to
``--metres`` and ``--degrees`` (a turn about the world's vertical axis through the first camera's centre,
and a shift), as a SLAM system's odometry drifts before it closes a loop; the frames after them come with
exact poses (the SLAM has closed its loop). Three maps: ``exact`` (exact poses throughout), ``uncorrected``
(the drift kept) and ``corrected`` (after the drifting frames, ``Mapper.correct_poses`` sends every
keyframe's exact pose, as ``CorrectPoses`` would). Each is scored when mapping ends on the held-out frames
(index % 10 == 5, never streamed) at their exact poses: mean PSNR raw and affine-fit, the gap to the exact
map, and the raw PSNR per stretch of ``--stretch`` frames. ``--modes`` maps a subset (each map is independent, so
long sequences can be mapped in separate processes side by side; ``exact`` equals ``bench/forgetting.py``'s map
of the same frames and seed).

    .venv/bin/python bench/loop_closure.py --data synthetic --frames 0:60 --drift-frames 40
    .venv/bin/python bench/loop_closure.py --data ../shared/data/7scenes-redkitchen --frames 0:600 \\
        --drift-frames 270
"""

from __future__ import annotations

import argparse
import time

import ogmapping  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its thread pool)

# isort: split
import dataclasses

import numpy as np
from sequence import add_sequence_arguments, load_sequence

from ogmapping.config import MapperConfig, parse_override_args, resolve
from ogmapping.frames.frame import Frame
from ogmapping.frames.rotation import axis_angle_matrix
from ogmapping.mapper import Mapper
from ogmapping.quality.evaluation import ground_truth, mapper_render, score

MODES = ("exact", "uncorrected", "corrected")


def drift(fraction: float, metres: float, degrees: float, up: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """A world motion of ``fraction`` of the full drift: a turn about ``up`` through ``centre``, then a shift
    at right angles to ``up``."""
    motion = np.eye(4)
    turn = axis_angle_matrix(up, np.radians(degrees * fraction))
    side = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    motion[:3, :3] = turn
    motion[:3, 3] = centre - turn @ centre + side / np.linalg.norm(side) * metres * fraction
    return motion


def map_run(mode: str, frames: list[Frame], args: argparse.Namespace, config: MapperConfig) -> Mapper:
    mapper = Mapper(config)
    exact = {frame.index: frame.c2w.copy() for frame in frames}
    # The world's vertical as the first camera sees it (its image's up), the turn's centre its position.
    up, centre = -frames[0].c2w[:3, 1], frames[0].c2w[:3, 3]
    for number, frame in enumerate(frames):
        if mode != "exact" and number < args.drift_frames:
            motion = drift((number + 1) / args.drift_frames, args.metres, args.degrees, up, centre)
            frame = dataclasses.replace(frame, c2w=motion @ frame.c2w)
        mapper.process(frame)
        if mode == "corrected" and number == args.drift_frames - 1:
            mapper.correct_poses({position: exact[keyframe.index]
                                  for position, keyframe in enumerate(mapper.keyframes.keyframes)})
    return mapper


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_sequence_arguments(parser)
    parser.set_defaults(data="synthetic", frames="0:60")
    parser.add_argument("--drift-frames", type=int, default=40, help="streamed frames that drift (default 40)")
    parser.add_argument("--metres", type=float, default=0.10, help="drift at its end (default 0.10)")
    parser.add_argument("--degrees", type=float, default=3.0, help="drift at its end (default 3)")
    parser.add_argument("--stretch", type=int, default=60, help="frames per stretch in the summary (default 60)")
    parser.add_argument("--modes", default=",".join(MODES),
                        help=f"comma-separated maps to make, of {', '.join(MODES)} (default all)")
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="config overrides")
    args = parser.parse_args()
    modes = [mode for mode in args.modes.split(",") if mode]
    if not modes or set(modes) - set(MODES):
        parser.error(f"--modes takes a comma-separated list of {', '.join(MODES)} (got {args.modes!r})")
    sequence = load_sequence(args)
    streamed, held = sequence.streamed, sequence.heldout
    if not 0 < args.drift_frames <= len(streamed):
        parser.error(f"--drift-frames must be 1 to {len(streamed)}, the streamed frames (got {args.drift_frames})")
    config = resolve(args.preset, overrides=parse_override_args(args.set))
    truths = [ground_truth(frame, config) for frame in held]
    size = f"{streamed[0].color_intrinsics.width}x{streamed[0].color_intrinsics.height}"
    print(f"{args.data} {args.frames}: {len(streamed)} frames streamed ({args.drift_frames} drifting to "
          f"{args.metres:g} m and {args.degrees:g} degrees), {len(held)} held out, {size}, {args.preset} "
          f"{' '.join(args.set)}", flush=True)
    exact = None
    for mode in modes:
        start = time.perf_counter()
        mapper = map_run(mode, streamed, args, config)
        render = mapper_render(mapper)
        scores = [score(render(truth.c2w, truth.color_intrinsics, truth), truth) for truth in truths]
        raw = np.array([each["psnr"] for each in scores])
        affine = np.mean([each["psnr_affine"] for each in scores])
        exact = raw.mean() if mode == "exact" else exact
        gap = "" if exact is None else f" (gap to exact {raw.mean() - exact:+.2f} dB)"
        stretches: dict[int, list[float]] = {}
        for truth, value in zip(truths, raw, strict=True):
            stretches.setdefault((truth.index - truths[0].index) // args.stretch, []).append(value)
        summary = " / ".join(f"{np.mean(each):.2f}" for _, each in sorted(stretches.items()))
        print(f"{mode:12s} held-out PSNR at the exact poses {raw.mean():6.2f} dB{gap}, "
              f"affine-fit {affine:.2f} dB, per {args.stretch} frames {summary}, "
              f"{time.perf_counter() - start:.0f} s", flush=True)


if __name__ == "__main__":
    main()
