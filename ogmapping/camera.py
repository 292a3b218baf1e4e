"""Camera and pose conventions, in one place so every module agrees.

- Poses are camera-to-world 4x4 matrices (``c2w``), metres.
- Camera axes follow OpenCV: x right, y down, z forward.
- Pixel (row i, column j) covers [j, j+1) x [i, i+1) and its centre is (j + 0.5, i + 0.5).
  This is gsplat's convention; with it, resizing an image by ``s`` scales fx, fy, cx, cy by ``s``.
- Depth is metres along the camera z axis; 0 (or non-finite) marks an invalid pixel.
- Quaternions are (w, x, y, z).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

ORTHONORMAL_TOLERANCE = 1e-2


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of one image size."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def scaled(self, scale: float) -> Intrinsics:
        """Intrinsics of the same camera with the image resized by ``scale``."""
        return Intrinsics(
            self.fx * scale,
            self.fy * scale,
            self.cx * scale,
            self.cy * scale,
            round(self.width * scale),
            round(self.height * scale),
        )

    def resized(self, width: int, height: int) -> Intrinsics:
        """Intrinsics after resizing the image to exactly ``width`` x ``height``."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, width, height)

    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def tensor(self, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> torch.Tensor:
        return torch.as_tensor(self.matrix(), dtype=dtype, device=device)

    @classmethod
    def from_matrix(cls, k: np.ndarray, width: int, height: int) -> Intrinsics:
        k = np.asarray(k, dtype=np.float64)
        return cls(float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]), int(width), int(height))

    def validate(self) -> None:
        """Raise ValueError naming the first field that cannot describe a real camera."""
        for name in ("fx", "fy", "cx", "cy"):
            value = getattr(self, name)
            if not np.isfinite(value):
                raise ValueError(f"intrinsics.{name} is not finite ({value})")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"intrinsics.fx/fy must be positive (got {self.fx}, {self.fy})")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"intrinsics width/height must be positive (got {self.width}x{self.height})")


def validate_pose(c2w: np.ndarray, name: str = "pose") -> np.ndarray:
    """Return ``c2w`` as float64 4x4, or raise ValueError saying what is wrong with it."""
    pose = np.asarray(c2w, dtype=np.float64)
    if pose.shape != (4, 4):
        raise ValueError(f"{name} must be 4x4 (got shape {pose.shape})")
    if not np.all(np.isfinite(pose)):
        raise ValueError(f"{name} has non-finite entries")
    if not np.allclose(pose[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
        raise ValueError(f"{name} last row must be [0, 0, 0, 1] (got {pose[3].tolist()})")
    rotation = pose[:3, :3]
    error = np.abs(rotation @ rotation.T - np.eye(3)).max()
    if error > ORTHONORMAL_TOLERANCE:
        raise ValueError(f"{name} rotation is not orthonormal (max |R R^T - I| = {error:.3g})")
    if np.linalg.det(rotation) < 0:
        raise ValueError(f"{name} rotation is a reflection (det < 0)")
    return pose


def world_to_camera(c2w: torch.Tensor) -> torch.Tensor:
    """Invert a rigid camera-to-world transform without a general matrix inverse."""
    rotation = c2w[..., :3, :3]
    translation = c2w[..., :3, 3:]
    w2c = torch.zeros_like(c2w)
    w2c[..., :3, :3] = rotation.transpose(-1, -2)
    w2c[..., :3, 3:] = -rotation.transpose(-1, -2) @ translation
    w2c[..., 3, 3] = 1.0
    return w2c


def pixel_rays(intrinsics: Intrinsics, device: torch.device | str = "cpu") -> torch.Tensor:
    """Camera-space ray directions with z = 1 through every pixel centre, shape (H, W, 3)."""
    rows = torch.arange(intrinsics.height, device=device, dtype=torch.float32) + 0.5
    cols = torch.arange(intrinsics.width, device=device, dtype=torch.float32) + 0.5
    v, u = torch.meshgrid(rows, cols, indexing="ij")
    x = (u - intrinsics.cx) / intrinsics.fx
    y = (v - intrinsics.cy) / intrinsics.fy
    return torch.stack([x, y, torch.ones_like(x)], dim=-1)


def backproject(depth: torch.Tensor, intrinsics: Intrinsics, c2w: torch.Tensor) -> torch.Tensor:
    """World points of every valid depth pixel, shape (M, 3)."""
    valid = torch.isfinite(depth) & (depth > 0)
    rays = pixel_rays(intrinsics, depth.device)[valid]
    points_camera = rays * depth[valid].unsqueeze(-1)
    return points_camera @ c2w[:3, :3].T.to(points_camera) + c2w[:3, 3].to(points_camera)


def project(points: torch.Tensor, intrinsics: Intrinsics, c2w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel coordinates (M, 2) and camera depth (M,) of world points."""
    w2c = world_to_camera(c2w.to(points))
    camera = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = camera[:, 2]
    safe_z = torch.where(z.abs() > 1e-9, z, torch.full_like(z, 1e-9))
    u = intrinsics.fx * camera[:, 0] / safe_z + intrinsics.cx
    v = intrinsics.fy * camera[:, 1] / safe_z + intrinsics.cy
    return torch.stack([u, v], dim=-1), z


def in_frustum(
    points: torch.Tensor, intrinsics: Intrinsics, c2w: torch.Tensor, near: float = 0.05, far: float = 100.0,
    margin: float = 0.0,
) -> torch.Tensor:
    """Which world points project inside the image (grown by ``margin`` pixels) between near and far."""
    uv, z = project(points, intrinsics, c2w)
    return (
        (z > near)
        & (z < far)
        & (uv[:, 0] >= -margin)
        & (uv[:, 0] <= intrinsics.width + margin)
        & (uv[:, 1] >= -margin)
        & (uv[:, 1] <= intrinsics.height + margin)
    )
