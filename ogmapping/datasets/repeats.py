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

from ogmapping.frames.rotation import interpolate_pose


def same_bytes(first: Path, second: Path) -> bool:
    """True when the two files hold the same bytes (sizes compared first, so a differing pair reads nothing)."""
    return first.stat().st_size == second.stat().st_size and first.read_bytes() == second.read_bytes()


def colour_time_pose(
    position: int,
    colours: Sequence[Path],
    depths: Sequence[Path],
    pose: Callable[[int], np.ndarray],
    adjacent: Callable[[int], bool],
) -> np.ndarray | None:
    """The camera pose at the time of ``position``'s colour image where a repeat moves it from ``pose(position)``;
    None where it does not. ``adjacent(p)``: frame ``p`` directly follows frame ``p - 1`` in the recording."""
    if position == 0 or not adjacent(position):
        return None
    colour_repeats = same_bytes(colours[position - 1], colours[position])
    depth_repeats = same_bytes(depths[position - 1], depths[position])
    if colour_repeats == depth_repeats:
        return None
    if colour_repeats:
        earlier = colour_time_pose(position - 1, colours, depths, pose, adjacent)
        return pose(position - 1) if earlier is None else earlier
    if position + 1 >= len(depths) or not adjacent(position + 1):
        return None
    return interpolate_pose(pose(position - 1), pose(position + 1), 0.5)
