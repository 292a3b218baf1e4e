"""EWA projection of 3D Gaussians to screen-space ellipses: the definition every backend follows.

Pure torch so autograd carries gradients from ``means2d``/``conics``/``depths`` back to the
Gaussian parameters; only the integer ``radii`` are computed without gradients. The reference
backend uses it directly; the cpu backend runs a fused Numba copy (``cpu_projection.py``) that
tests hold equal to this one, and shares its ``Projection`` type and constants.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from ogmapping.frames.rotation import quaternion_entries
from ogmapping.render.rules import ALPHA_MIN, COVARIANCE_BLUR, NEAR_PLANE

# Off-axis limit of the Jacobian, as a fraction of the half field of view beyond the image edge:
# far off-screen Gaussians would otherwise get wildly stretched 2D footprints (as in 3DGS).
FOV_MARGIN = 0.3
# Radii are stored as int32; this caps them far beyond any image while staying representable.
RADIUS_CAP = 2**30
# Gaussians per projection chunk: keeps the (N,) ops below torch's parallel grain size (32768).
PROJECTION_CHUNK = 24576


@dataclass
class Projection:
    """Per-Gaussian screen-space quantities; ``radii == 0`` marks culled Gaussians."""

    means2d: torch.Tensor  # (N, 2) pixels
    conics: torch.Tensor  # (N, 3) inverse 2D covariance (a, b, c): [[a, b], [b, c]]
    depths: torch.Tensor  # (N,) camera z
    radii: torch.Tensor  # (N,) int32, 0 = culled


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
    blur: float = COVARIANCE_BLUR,
) -> Projection:
    """Project Gaussians into a pinhole camera and cull those that cannot touch any pixel.

    Culled: centre nearer than NEAR_PLANE (or behind), opacity below ALPHA_MIN, a degenerate 2D
    covariance, or a bounding square that misses the image. The radius bounds exactly the ellipse
    where ``opacity * exp(-0.5 d^T conic d) >= ALPHA_MIN``, so tile binning never drops a pixel.

    Runs in chunks of PROJECTION_CHUNK Gaussians: the projection is ~100 small elementwise ops,
    and below torch's parallel grain size each runs inline instead of waking the thread pool,
    which (with the project's passive OpenMP wait policy) makes it about twice as fast.
    """
    n = means.shape[0]
    if n <= PROJECTION_CHUNK:
        return _project_chunk(means, quats, scales, opacities, viewmat, K, width, height, blur)
    parts = [
        _project_chunk(
            means[s:s + PROJECTION_CHUNK], quats[s:s + PROJECTION_CHUNK], scales[s:s + PROJECTION_CHUNK],
            opacities[s:s + PROJECTION_CHUNK], viewmat, K, width, height, blur,
        )
        for s in range(0, n, PROJECTION_CHUNK)
    ]
    return Projection(
        torch.cat([p.means2d for p in parts]),
        torch.cat([p.conics for p in parts]),
        torch.cat([p.depths for p in parts]),
        torch.cat([p.radii for p in parts]),
    )


def _project_chunk(
    means: torch.Tensor,
    quats: torch.Tensor,
    scales: torch.Tensor,
    opacities: torch.Tensor,
    viewmat: torch.Tensor,
    K: torch.Tensor,
    width: int,
    height: int,
    blur: float,
) -> Projection:
    """``project_gaussians`` on one chunk of Gaussians."""
    viewmat = viewmat.to(means)
    K = K.to(means)
    # The camera-frame centre term by term, summed in the order the cpu backend's kernel sums it,
    # not as a matmul: a matmul's rounding is the BLAS kernel's (MKL's AVX-512 one on Intel Xeons
    # rounds a quarter of the depths of a map one ulp off the kernel's), and one ulp reorders
    # Gaussians of equal depth, which changes the image where they overlap.
    w = [[viewmat[i, j] for j in range(4)] for i in range(3)]
    mx, my, mz = means.unbind(-1)
    x, y, z = (w[i][0] * mx + w[i][1] * my + w[i][2] * mz + w[i][3] for i in range(3))
    in_front = z >= NEAR_PLANE
    z_safe = torch.where(in_front, z, torch.ones_like(z))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    x_z = x / z_safe
    y_z = y / z_safe
    means2d = torch.stack([fx * x_z + cx, fy * y_z + cy], dim=-1)

    # Everything below is written per component on (N,) tensors: batched 3x3 matmuls and
    # broadcasts over small trailing dimensions are several times slower in torch, forward and
    # backward, and this is on the mapper's hot path.
    half_tan_x = 0.5 * width / fx
    half_tan_y = 0.5 * height / fy
    tx = torch.clamp(x_z, -(cx / fx + FOV_MARGIN * half_tan_x), (width - cx) / fx + FOV_MARGIN * half_tan_x)
    ty = torch.clamp(y_z, -(cy / fy + FOV_MARGIN * half_tan_y), (height - cy) / fy + FOV_MARGIN * half_tan_y)
    # Rows of J @ W: perspective Jacobian times the world-to-camera rotation.
    gx = fx / z_safe
    gy = fy / z_safe
    jw0 = [gx * (w[0][k] - tx * w[2][k]) for k in range(3)]
    jw1 = [gy * (w[1][k] - ty * w[2][k]) for k in range(3)]
    # T = J W R S, R S being the Gaussian's axes scaled by its standard deviations.
    rot = quaternion_entries(*torch.nn.functional.normalize(quats, dim=-1).unbind(-1))  # (w, x, y, z)
    s = scales.unbind(-1)
    t0 = [s[j] * (jw0[0] * rot[0][j] + jw0[1] * rot[1][j] + jw0[2] * rot[2][j]) for j in range(3)]
    t1 = [s[j] * (jw1[0] * rot[0][j] + jw1[1] * rot[1][j] + jw1[2] * rot[2][j]) for j in range(3)]
    # 2D covariance T T^T plus the blur that keeps sub-pixel Gaussians at least a pixel wide.
    a = t0[0] * t0[0] + t0[1] * t0[1] + t0[2] * t0[2] + blur
    b = t0[0] * t1[0] + t0[1] * t1[1] + t0[2] * t1[2]
    c = t1[0] * t1[0] + t1[1] * t1[1] + t1[2] * t1[2] + blur
    det = a * c - b * b
    valid = in_front & (det > 0) & (opacities >= ALPHA_MIN)
    det_safe = torch.where(valid, det, torch.ones_like(det))
    inv_det = 1.0 / det_safe
    conics = torch.stack([c * inv_det, -b * inv_det, a * inv_det], dim=-1)

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
