"""Colour images with their depth images, by header stamp.

Colour and depth come from separate streams (separate sensors, or one driver publishing each on
its own); a colour image takes the depth image nearest in time, one-to-one, closest pairs first,
within ``--pair-tolerance`` (as the TUM reader associates its lists). Images left without a
partner are counted for the report, not streamed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ogmapping.datasets.rosbag.bagfile import MessageRef
from ogmapping.datasets.tum import associate_unique


@dataclass(frozen=True)
class StampedImage:
    ref: MessageRef
    stamp_ns: int
    frame_id: str


@dataclass(frozen=True)
class Pairing:
    pairs: list[tuple[StampedImage, StampedImage]]  # (colour, depth), in colour stamp order
    unpaired_color: int
    unpaired_depth: int


def pair_images(colors: list[StampedImage], depths: list[StampedImage], tolerance_s: float) -> Pairing:
    if tolerance_s < 0:
        raise ValueError(f"--pair-tolerance must be at least 0 (got {tolerance_s})")
    if not colors or not depths:
        return Pairing([], len(colors), len(depths))
    origin = min(colors[0].stamp_ns, depths[0].stamp_ns)  # relative stamps stay exact in float64
    color_t = np.array([(c.stamp_ns - origin) * 1e-9 for c in colors])
    depth_t = np.array([(d.stamp_ns - origin) * 1e-9 for d in depths])
    # associate_unique wants a strict bound; a pair exactly at the tolerance is kept.
    matches = associate_unique(color_t, depth_t, tolerance_s + 1e-9)
    pairs = sorted(((colors[i], depths[j]) for i, j in matches), key=lambda pair: pair[0].stamp_ns)
    return Pairing(pairs, len(colors) - len(pairs), len(depths) - len(pairs))
