"""EWA projection of 3D Gaussians to screen-space ellipses, shared by the torch and cpu backends.

Pure torch so autograd carries gradients from ``means2d``/``conics``/``depths`` back to the
Gaussian parameters; only the integer ``radii`` are computed without gradients.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ogmapping.render import ALPHA_MIN, COVARIANCE_BLUR, NEAR_PLANE

# Off-axis limit of the Jacobian, as a fraction of the half field of view beyond the image edge:
# far off-screen Gaussians would otherwise get wildly stretched 2D footprints (as in 3DGS).
FOV_MARGIN = 0.3
# Radii are stored as int32; this caps them far beyond any image while staying representable.
RADIUS_CAP = 2**30


@dataclass
class Projection:
    """Per-Gaussian screen-space quantities; ``radii == 0`` marks culled Gaussians."""

    means2d: torch.Tensor  # (N, 2) pixels
    conics: torch.Tensor  # (N, 3) inverse 2D covariance (a, b, c): [[a, b], [b, c]]
    depths: torch.Tensor  # (N,) camera z
    radii: torch.Tensor  # (N,) int32, 0 = culled


def quat_to_rotmat(quats: torch.Tensor) -> torch.Tensor:
    """Rotation matrices (N, 3, 3) of (w, x, y, z) quaternions, normalised here."""
    q = torch.nn.functional.normalize(quats, dim=-1)
    w, x, y, z = q.unbind(-1)
    rows = (
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    )
    return torch.stack(rows, dim=-1).reshape(*quats.shape[:-1], 3, 3)


def alpha_extent(opacities: torch.Tensor) -> torch.Tensor:
    """Mahalanobis radius inside which ``opacity * exp(-0.5 d^2)`` stays >= ALPHA_MIN (0 below it)."""
    ratio = (opacities / ALPHA_MIN).clamp_min(1.0)
    return torch.sqrt(2.0 * torch.log(ratio))


def project_gaussians(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
) -> Projection:
    """Project Gaussians into a pinhole camera and cull those that cannot touch any pixel.

    Culled: centre nearer than NEAR_PLANE (or behind), opacity below ALPHA_MIN, a degenerate 2D
    covariance, or a bounding square that misses the image. The radius bounds exactly the ellipse
    where ``opacity * exp(-0.5 d^T conic d) >= ALPHA_MIN``, so tile binning never drops a pixel.
    """
    viewmat = viewmat.to(means)
    K = K.to(means)
    rotation_cw = viewmat[:3, :3]
    p_cam = means @ rotation_cw.T + viewmat[:3, 3]
    x, y, z = p_cam.unbind(-1)
    in_front = z >= NEAR_PLANE
    z_safe = torch.where(in_front, z, torch.ones_like(z))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    u = fx * x / z_safe + cx
    v = fy * y / z_safe + cy
    means2d = torch.stack([u, v], dim=-1)

    half_tan_x = 0.5 * width / fx
    half_tan_y = 0.5 * height / fy
    tx = torch.clamp(x / z_safe, -(cx / fx + FOV_MARGIN * half_tan_x), (width - cx) / fx + FOV_MARGIN * half_tan_x)
    ty = torch.clamp(y / z_safe, -(cy / fy + FOV_MARGIN * half_tan_y), (height - cy) / fy + FOV_MARGIN * half_tan_y)
    zeros = torch.zeros_like(z)
    jacobian = torch.stack(
        [fx / z_safe, zeros, -fx * tx / z_safe, zeros, fy / z_safe, -fy * ty / z_safe], dim=-1
    ).reshape(-1, 2, 3)

    m = quat_to_rotmat(quats) * scales.unsqueeze(-2)
    cov_world = m @ m.transpose(-1, -2)
    cov_cam = rotation_cw @ cov_world @ rotation_cw.T
    cov2d = jacobian @ cov_cam @ jacobian.transpose(-1, -2)
    a = cov2d[:, 0, 0] + COVARIANCE_BLUR
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + COVARIANCE_BLUR
    det = a * c - b * b
    valid = in_front & (det > 0) & (opacities >= ALPHA_MIN)
    det_safe = torch.where(valid, det, torch.ones_like(det))
    conics = torch.stack([c / det_safe, -b / det_safe, a / det_safe], dim=-1)

    radii = _radii(means2d.detach(), a.detach(), b.detach(), c.detach(), opacities.detach(), valid, width, height)
    return Projection(means2d, conics, z, radii)


def _radii(
    means2d: torch.Tensor,
    a: torch.Tensor,
    b: torch.Tensor,
    c: torch.Tensor,
    opacities: torch.Tensor,
    valid: torch.Tensor,
    width: int,
    height: int,
) -> torch.Tensor:
    """Integer bounding radius per Gaussian, 0 for culled ones (in float64 to keep the bound safe)."""
    a, b, c = a.double(), b.double(), c.double()
    half_trace = 0.5 * (a + c)
    lambda_max = half_trace + torch.sqrt((0.25 * (a - c) ** 2 + b * b).clamp_min(0.0))
    extent = alpha_extent(opacities.double()) * torch.sqrt(lambda_max.clamp_min(0.0))
    radius = torch.ceil(extent).clamp(1.0, float(RADIUS_CAP))
    u, v = means2d.double().unbind(-1)
    on_image = (u + radius > 0) & (u - radius < width) & (v + radius > 0) & (v - radius < height)
    keep = valid & on_image & torch.isfinite(extent) & torch.isfinite(u) & torch.isfinite(v)
    keep = keep & torch.isfinite(a) & torch.isfinite(b) & torch.isfinite(c)
    return torch.where(keep, radius, torch.zeros_like(radius)).to(torch.int32)


def tile_grid(width: int, height: int, tile: int) -> tuple[int, int]:
    """Number of tile columns and rows covering the image."""
    return math.ceil(width / tile), math.ceil(height / tile)
