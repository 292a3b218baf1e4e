"""The unit of input: one RGB-D frame with its pose, as every reader and the service produce it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ogmapping.frames.camera import Intrinsics


@dataclass
class Frame:
    """One RGB-D observation.

    ``rgb`` is float32 (H, W, 3) in [0, 1]; ``depth`` is float32 (Hd, Wd) in metres with 0 for
    invalid pixels. Colour and depth may come from different cameras: ``depth_intrinsics`` and the
    optional ``depth_to_color`` (4x4, depth camera frame to colour camera frame) describe the depth
    camera; ``c2w`` is the colour camera's pose. ``index`` is the frame's position in its source.
    """

    index: int
    rgb: np.ndarray
    depth: np.ndarray
    color_intrinsics: Intrinsics
    depth_intrinsics: Intrinsics
    c2w: np.ndarray
    timestamp: float | None = None  # seconds on the sensor clock; None when the source gave none
    depth_to_color: np.ndarray | None = None

    @property
    def registered(self) -> bool:
        """True when depth already lies on the colour image grid."""
        return self.depth_to_color is None and self.depth_intrinsics == self.color_intrinsics
