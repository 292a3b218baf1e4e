"""Captures sent twice: a colour or depth image byte-identical to the one of the frame before is that
earlier capture again, and is seen from the pose of its own time.

Some recordings drop a capture now and then and store the one before in its place, colour and depth each
on their own (7-Scenes RedKitchen from frame 222 on: 58 colour and 59 depth images, 42 of them both at
once). Its poses come from tracking the depth images it stored, so at a repeated depth image the pose
barely moves (1.1 mm median, against 8 mm between frames) and the next frame's catches up. Where both
images repeat, the frame is the earlier one whole, pose and all, and stays as it is. Where only the colour
image repeats, it is the earlier frame's, seen from the earlier frame's colour pose. Where only the depth
image repeats, the pose belongs to that earlier depth image, and the colour image, which is new, is seen
from halfway between the poses of the frames either side.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from ogmapping.datasets.base import FrameFiles
from ogmapping.frames.rotation import interpolate_pose


def same_bytes(first: Path, second: Path) -> bool:
    """True when the two files hold the same bytes (sizes compared first, so a differing pair reads nothing)."""
    return first.stat().st_size == second.stat().st_size and first.read_bytes() == second.read_bytes()


def colour_time_pose(
    position: int,
    files: Sequence[FrameFiles],
    pose: Callable[[int], np.ndarray],
    adjacent: Callable[[int], bool],
) -> np.ndarray | None:
    """The camera pose at the time of ``position``'s colour image where a repeat moves it from ``pose(position)``;
    None where it does not. ``adjacent(p)``: frame ``p`` directly follows frame ``p - 1`` in the recording."""

    def repeated(at: int) -> tuple[bool, bool]:
        """Whether frame ``at``'s colour and depth images repeat the frame before's."""
        if at == 0 or not adjacent(at):
            return False, False
        return (same_bytes(files[at - 1].color, files[at].color),
                same_bytes(files[at - 1].depth, files[at].depth))

    def halfway(at: int) -> np.ndarray | None:
        """Between the poses either side of ``at``, where it has a frame after it."""
        if at + 1 >= len(files) or not adjacent(at + 1):
            return None
        return interpolate_pose(pose(at - 1), pose(at + 1), 0.5)

    colour, depth = repeated(position)
    if colour == depth:
        return None
    if depth:
        return halfway(position)
    source = position - 1  # the frame whose colour image this is: back over a run of colour images alone
    while (kind := repeated(source)) == (True, False):
        source -= 1
    earlier = halfway(source) if kind == (False, True) else None
    return pose(source) if earlier is None else earlier
