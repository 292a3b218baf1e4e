"""Camera and pose conventions, in one place so every module agrees.

- Poses are camera-to-world 4x4 matrices (``c2w``), metres.
- Camera axes follow OpenCV: x right, y down, z forward.
- Pixel (row i, column j) covers [j, j+1) x [i, i+1) and its centre is (j + 0.5, i + 0.5).
  This is gsplat's convention; with it, resizing an image by ``s`` scales fx, fy, cx, cy by ``s``.
- Depth is metres along the camera z axis; 0 (or non-finite) marks an invalid pixel.
- The Gaussians' quaternions are (w, x, y, z); pose files (TUM, ROS, Foxglove) write (x, y, z, w),
  the order of ``ogmapping.frames.rotation``.

Plain numpy, so datasets, frames and the client use it without loading torch; the torch geometry
on these conventions (projection, back-projection, frustum tests) is in ``ogmapping.frames.geometry``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
        """Intrinsics of the same camera with the image resized by ``scale``; a side never shrinks
        below one pixel (a 100000x1 image at half size is 50000x1, not empty)."""
        return Intrinsics(
            self.fx * scale,
            self.fy * scale,
            self.cx * scale,
            self.cy * scale,
            max(1, round(self.width * scale)),
            max(1, round(self.height * scale)),
        )

    def resized(self, width: int, height: int) -> Intrinsics:
        """Intrinsics after resizing the image to exactly ``width`` x ``height``."""
        sx, sy = width / self.width, height / self.height
        return Intrinsics(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, width, height)

    def strided(self, stride: int, start: int) -> Intrinsics:
        """Intrinsics of ``image[start::stride, start::stride]``: its pixel j is the original pixel
        start + j * stride, centres included."""
        shift = start + 0.5 - stride / 2
        return Intrinsics(self.fx / stride, self.fy / stride, (self.cx - shift) / stride, (self.cy - shift) / stride,
                          len(range(start, self.width, stride)), len(range(start, self.height, stride)))

    def matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

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
