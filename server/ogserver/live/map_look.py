"""What the live views ask of one session's map: a render from a pose, its Gaussians as a .ply, a bounded
point cloud, its statistics and keyframes' path. ``MapperLook`` answers from a mapper in this process; a
session in a worker process answers the same questions through its worker (``workers/views.py``), so the
web view and the Foxglove view are written once for both.
"""

from __future__ import annotations

from contextlib import AbstractContextManager
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from ogapi.images import encode_color
from ogapi.v1 import mapping_pb2 as pb

from ogmapping.frames.camera import Intrinsics
from ogmapping.mapper import Mapper
from ogmapping.persist.export import ColoredPoints, default_viewpoint, ply_bytes, point_cloud
from ogmapping.stats import MapStats

RENDER_JPEG_QUALITY = 90


@dataclass(frozen=True)
class Splats:
    """A map's Gaussians decoded as seen from one point, as a 3DGS .ply, and how many there are."""

    ply: bytes
    count: int


class MapLook(Protocol):
    # Held around each decode or render to count it (``web.maps.Busy``): the mapper's lock in its own process;
    # nothing for a map in a worker, which holds its mapper's lock there.
    lock: AbstractContextManager[Any]

    def refines(self) -> bool:
        """Whether the session refines poses (``poses.refine``): its views show both camera paths."""
        ...

    def viewpoint(self) -> np.ndarray:
        """Where the map is seen from by default: the mapped cameras' centroid, else the anchors' mean."""
        ...

    def anchor_centroid(self) -> np.ndarray: ...

    def splats(self, center: np.ndarray) -> Splats: ...

    def render_jpeg(self, c2w: np.ndarray, intrinsics: Intrinsics) -> bytes: ...

    def points(self, max_points: int) -> ColoredPoints:
        """At most ``max_points`` Gaussians, coloured as seen from ``viewpoint``."""
        ...

    def stats(self) -> MapStats: ...

    def keyframe_path(self) -> np.ndarray:
        """The keyframes' refined camera-to-world poses (n, 4, 4), in mapping order."""
        ...


class MapperLook:
    """A mapper's answers; each takes the mapper's lock, between optimisation iterations, like a Render call."""

    def __init__(self, mapper: Mapper) -> None:
        self.mapper = mapper
        self.lock = mapper.lock

    def refines(self) -> bool:
        return self.mapper.config.poses.refine

    def viewpoint(self) -> np.ndarray:
        return default_viewpoint(self.mapper).center

    def anchor_centroid(self) -> np.ndarray:
        return self.mapper.anchor_centroid()

    def splats(self, center: np.ndarray) -> Splats:
        gaussians = self.mapper.decode_at(center)
        return Splats(ply_bytes(gaussians), int(gaussians.means.shape[0]))

    def render_jpeg(self, c2w: np.ndarray, intrinsics: Intrinsics) -> bytes:
        return encode_color(self.mapper.render(c2w, intrinsics).color, pb.COLOR_JPEG, RENDER_JPEG_QUALITY)

    def points(self, max_points: int) -> ColoredPoints:
        return point_cloud(self.mapper, self.viewpoint(), max_points)

    def stats(self) -> MapStats:
        return self.mapper.stats()

    def keyframe_path(self) -> np.ndarray:
        return keyframe_path(self.mapper)


def keyframe_path(mapper: Mapper) -> np.ndarray:
    """A mapper's keyframes' refined camera-to-world poses (n, 4, 4), in mapping order."""
    return np.array([pose.refined_c2w for pose in mapper.keyframe_poses()]).reshape(-1, 4, 4)
