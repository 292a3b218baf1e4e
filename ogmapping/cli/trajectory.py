"""``ogmap trajectory``: a dataset's poses as a TUM file, optionally moved by seeded noise; and the check
``ogmap run`` makes that trajectory files cover every frame it will stream or judge.

Poses do not depend on the image scale, so frames are read at the source's size (no resizing); reading
them still decodes their images, the one way every reader offers.
"""

from __future__ import annotations

import argparse
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
from tqdm import tqdm

from ogmapping.cli.options import open_frame_set
from ogmapping.frames.frame import Frame
from ogmapping.frames.trajectory import Trajectory, frame_key, perturb, pose_errors, write_tum
from ogmapping.quality.evaluation import FrameSet


def source_frames(frames: FrameSet, desc: str, progress: bool) -> Iterator[Frame]:
    """The selected frames (streamed and held out, in source order) as the source gives them."""
    for position in tqdm(frames.positions, desc=desc, unit="frame", disable=not progress):
        yield frames.source[position]


def check_covers(frames: FrameSet, trajectories: Sequence[Trajectory], progress: bool) -> None:
    """ValueError naming the first selected frame one of ``trajectories`` has no pose for."""
    if not trajectories:
        return
    for frame in source_frames(frames, "checking poses", progress):
        for trajectory in trajectories:
            trajectory.pose_of(frame)


def dataset_poses(frames: FrameSet, progress: bool) -> tuple[list[float], np.ndarray]:
    """Keys (``frame_key``) and the data's c2w of the selected frames."""
    keys, poses = [], []
    for frame in source_frames(frames, "reading poses", progress):
        keys.append(frame_key(frame))
        poses.append(frame.c2w)
    return keys, np.stack(poses).astype(np.float64)


def command_trajectory(args: argparse.Namespace) -> int:
    frames = open_frame_set(args)
    keys, exact = dataset_poses(frames, not args.quiet)
    noisy = args.noise_translation != 0 or args.noise_rotation != 0
    poses = perturb(exact, args.noise_translation, args.noise_rotation, args.noise_seed) if noisy else exact
    selection = frames.selection
    comments = [f"{frames.source.name}, frames {args.frames or 'all'}, stride {args.stride}: "
                f"{len(selection.streamed)} streamed, {len(selection.heldout)} held out; camera-to-world, OpenCV axes"]
    if noisy:
        comments.append(f"noise: {args.noise_translation} m per axis, {args.noise_rotation} deg about a random axis, "
                        f"seed {args.noise_seed}; the first pose exact")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    write_tum(args.out, keys, poses, comments)
    line = (f"wrote {len(keys)} poses ({len(selection.streamed)} streamed, {len(selection.heldout)} held out) "
            f"to {args.out}")
    if noisy:
        distances, angles = pose_errors(poses[1:], exact[1:])
        mean_cm = 100 * float(distances.mean()) if len(distances) else 0.0
        mean_deg = float(angles.mean()) if len(angles) else 0.0
        line += f"; noise seed {args.noise_seed}: mean error {mean_cm:.2f} cm, {mean_deg:.3f} deg (first pose exact)"
    print(line)
    return 0
