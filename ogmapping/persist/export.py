"""Export the decoded Gaussians as a standard 3DGS ``.ply`` (binary little-endian), or as a
bounded coloured point cloud for live previews.

A .ply holds one colour per Gaussian, but this map's colours and opacities depend on the viewpoint
through the decoders, so an export fixes them as seen from one point. By default that point is
the centroid of every camera position the map was built from (kept in snapshots): renders of the
.ply then agree with the map's own renders near the trajectory. A point inside the scene (the
anchors' mean, all that older snapshots allow) is seen from no camera and agrees far less.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
import torch

from ogmapping.config import MapperConfig
from ogmapping.model.gaussians import GaussianSet

SH_C0 = 0.28209479177387814  # zeroth spherical-harmonic basis constant, 3DGS's colour encoding


class Decodable(Protocol):
    """What an export reads of a map (``ogmapping.mapper.Mapper``, which imports this package, not the
    other way round): its Gaussians decoded as seen from a point, and where its cameras were."""

    config: MapperConfig

    def decode_at(self, camera_center: np.ndarray, max_anchors: int = 0) -> GaussianSet: ...

    def camera_centroid(self) -> np.ndarray | None: ...

    def anchor_centroid(self) -> np.ndarray: ...


@dataclass(frozen=True)
class Viewpoint:
    """Where view-dependent colour is baked, and why there (for the user's message)."""

    center: np.ndarray
    origin: str


def default_viewpoint(mapper: Decodable) -> Viewpoint:
    """The mapped cameras' centroid, or the anchors' mean for a snapshot that has none on record."""
    centroid = mapper.camera_centroid()
    if centroid is not None:
        return Viewpoint(centroid, "the centroid of the mapped camera positions")
    return Viewpoint(mapper.anchor_centroid(), "the anchors' mean: this snapshot records no camera positions, "
                     "pass --center or --pose for a point near the views you care about")


def export_ply(mapper: Decodable, path: str | Path, camera_center: np.ndarray) -> int:
    """Write the map's Gaussians, decoded as seen from ``camera_center``, to ``path``; returns how many."""
    gaussians = mapper.decode_at(camera_center)
    with open(path, "wb") as handle:
        handle.write(ply_bytes(gaussians))
    return gaussians.means.shape[0]


@dataclass(frozen=True)
class SplatArrays:
    """Gaussians as 3DGS files hold them (float32 arrays): the .ply's and the .spz's source."""

    means: np.ndarray  # (N, 3)
    log_scales: np.ndarray  # (N, 3)
    quats: np.ndarray  # (N, 4) unit, w first
    logit_opacities: np.ndarray  # (N,)
    sh_dc: np.ndarray  # (N, 3) colour as the zeroth spherical-harmonic coefficient


def splat_arrays(gaussians: GaussianSet) -> SplatArrays:
    opacity = gaussians.opacities.clamp(1e-6, 1 - 1e-6).cpu().numpy()
    return SplatArrays(
        means=gaussians.means.cpu().numpy().astype(np.float32),
        log_scales=np.log(np.maximum(gaussians.scales.cpu().numpy(), 1e-12)).astype(np.float32),
        quats=torch.nn.functional.normalize(gaussians.quats, dim=-1).cpu().numpy().astype(np.float32),
        logit_opacities=np.log(opacity / (1 - opacity)).astype(np.float32),
        sh_dc=((gaussians.colors.cpu().numpy() - 0.5) / SH_C0).astype(np.float32),
    )


def ply_bytes(gaussians: GaussianSet) -> bytes:
    """Decoded Gaussians as a standard 3DGS .ply file's bytes."""
    splats = splat_arrays(gaussians)
    count = splats.means.shape[0]
    columns = {
        "x": splats.means[:, 0], "y": splats.means[:, 1], "z": splats.means[:, 2],
        "nx": np.zeros(count), "ny": np.zeros(count), "nz": np.zeros(count),
        **{f"f_dc_{axis}": splats.sh_dc[:, axis] for axis in range(3)},
        "opacity": splats.logit_opacities,
        **{f"scale_{axis}": splats.log_scales[:, axis] for axis in range(3)},
        **{f"rot_{axis}": splats.quats[:, axis] for axis in range(4)},
    }
    table = np.zeros(count, dtype=[(name, "<f4") for name in columns])
    for name, values in columns.items():
        table[name] = values
    header = "ply\nformat binary_little_endian 1.0\n" f"element vertex {count}\n"
    header += "".join(f"property float {name}\n" for name in columns) + "end_header\n"
    return header.encode("ascii") + table.tobytes()


@dataclass(frozen=True)
class ColoredPoints:
    """Gaussian centres with their colour and opacity as seen from one point: a preview of the map."""

    positions: np.ndarray  # (N, 3) float32, world
    rgba: np.ndarray  # (N, 4) uint8: colour, and opacity as alpha


def point_cloud(mapper: Decodable, camera_center: np.ndarray, max_points: int) -> ColoredPoints:
    """At most ``max_points`` of the map's Gaussians, from anchors spread evenly over the map (each
    anchor decodes ``n_offsets`` Gaussians), coloured as seen from ``camera_center``."""
    per_anchor = max(mapper.config.model.n_offsets, 1)
    gaussians = mapper.decode_at(camera_center, max_anchors=max(max_points // per_anchor, 1))
    keep = slice(0, max_points)
    rgba = torch.cat([gaussians.colors[keep].clamp(0, 1), gaussians.opacities[keep, None].clamp(0, 1)], dim=1)
    return ColoredPoints(
        positions=gaussians.means[keep].cpu().numpy().astype(np.float32),
        rgba=(rgba * 255).round().to(torch.uint8).cpu().numpy(),
    )
