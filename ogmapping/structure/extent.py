"""How far from the origin a map can reach, and how far one frame's points can land.

Anchor cells are Morton-coded (``ogmapping.structure.morton``): each axis holds 2^21 cells of a level, so the
finest level (``voxel_size / 4**max_level``) spans +-2^20 of its cells around the origin, about
+-6.5 km at the default 0.1 m and level 2. A frame whose points land outside cannot be mapped, and
growth places anchors a little beyond the observed surface, so frames must keep inside a share
of the range. The check needs only the pose, the intrinsics and the depth range, so a server
makes it before decoding or recording anything.
"""

from __future__ import annotations

import numpy as np

from ogmapping.config import OctreeConfig
from ogmapping.frames.camera import Intrinsics
from ogmapping.structure import morton

USABLE_SHARE = 0.9  # of the octree's range; the rest is margin for anchors grown beyond the observed surface


def map_radius(config: OctreeConfig) -> float:
    """Metres from the origin (per axis) within which frames may place points."""
    finest_cell = config.voxel_size / 4**config.max_level
    return USABLE_SHARE * (morton.COORD_MAX + 1) * finest_cell


def frame_radius(c2w: np.ndarray, intrinsics: Intrinsics, depth_max: float) -> float:
    """The largest coordinate (per axis, metres) any point of the frame can have: its depth is clipped to
    ``depth_max`` along rays through the image, the farthest of which passes through a corner."""
    corners_u = np.array([0.0, intrinsics.width])
    corners_v = np.array([0.0, intrinsics.height])
    ray_x = np.abs((corners_u - intrinsics.cx) / intrinsics.fx).max()
    ray_y = np.abs((corners_v - intrinsics.cy) / intrinsics.fy).max()
    longest_ray = float(np.sqrt(ray_x**2 + ray_y**2 + 1.0))
    return float(np.abs(c2w[:3, 3]).max()) + depth_max * longest_ray


def check_frame(c2w: np.ndarray, intrinsics: Intrinsics, config: OctreeConfig) -> None:
    """ValueError for a frame whose points could land beyond ``map_radius``: the engine codes a frame's cells
    without testing each (a test on the device would make the host wait), so the pose is checked instead."""
    reach, radius = frame_radius(c2w, intrinsics, config.depth_max), map_radius(config)
    if reach > radius:
        raise ValueError(f"the frame's points can land up to {reach:.0f} m from the origin along an axis; the map "
                         f"reaches {radius:.0f} m (set by octree.voxel_size and octree.max_level)")
