"""``sensor_msgs/CameraInfo`` to our intrinsics, and the undistortion its distortion model asks for.

K is published with integer pixel centres (OpenCV) and gets +0.5 on cx, cy. An image with zero
distortion is used as recorded, with K. Non-zero ``plumb_bob`` or ``rational_polynomial``
distortion is removed with OpenCV (``initUndistortRectifyMap``) onto the rectified camera P[:3, :3]
(K where P is all zero), the camera ``image_proc`` would give; colour is resampled bilinearly and
depth by nearest neighbour, so no depth is blended across an edge. Other models with non-zero
distortion are refused. ``describe`` says which of these happened, for the reader's report.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ogmapping.datasets.base import opencv_intrinsics
from ogmapping.datasets.rosbag.images import check_pixels
from ogmapping.frames.camera import Intrinsics

UNDISTORTED_MODELS = ("plumb_bob", "rational_polynomial")


def _field(message: object, name: str) -> object:
    """ROS 2 spells CameraInfo's matrices d, k, r, p; ROS 1 spells them D, K, R, P."""
    return getattr(message, name) if hasattr(message, name) else getattr(message, name.upper())


@dataclass(frozen=True)
class Calibration:
    """One camera's calibration, as recorded and as the reader hands frames on."""

    width: int
    height: int
    k: np.ndarray  # 3x3, integer pixel centres
    p: np.ndarray  # 3x3 of P, the rectified camera
    model: str
    distortion: np.ndarray

    @classmethod
    def from_message(cls, message: object) -> Calibration:
        width, height = int(message.width), int(message.height)  # type: ignore[attr-defined]
        k = np.asarray(_field(message, "k"), dtype=np.float64).reshape(3, 3)
        p = np.asarray(_field(message, "p"), dtype=np.float64).reshape(3, 4)[:, :3]
        calibration = cls(width, height, k, p if p[0, 0] > 0 and p[1, 1] > 0 else k,
                          str(message.distortion_model), np.asarray(_field(message, "d"), dtype=np.float64))  # type: ignore[attr-defined]
        calibration.check()
        _check_full_frame(message, width, height)
        return calibration

    def check(self) -> None:
        """ValueError for a calibration no image can be used with."""
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"CameraInfo has no image size ({self.width}x{self.height})")
        check_pixels(self.width, self.height)
        if not (np.isfinite(self.k).all() and self.k[0, 0] > 0 and self.k[1, 1] > 0):
            raise ValueError(f"CameraInfo K has no positive focal lengths: {self.k.ravel().tolist()}")
        if self.distorted and self.model not in UNDISTORTED_MODELS:
            raise ValueError(f"CameraInfo distortion model {self.model!r} with non-zero coefficients "
                             f"{self.distortion.tolist()} is not supported; expected {' or '.join(UNDISTORTED_MODELS)}")

    @property
    def distorted(self) -> bool:
        return bool(np.any(self.distortion != 0.0))

    @property
    def rectified(self) -> np.ndarray:
        """The 3x3 camera of the images handed on: P after undistortion, else K."""
        return self.p if self.distorted else self.k

    def intrinsics(self) -> Intrinsics:
        m = self.rectified
        return opencv_intrinsics(m[0, 0], m[1, 1], m[0, 2], m[1, 2], self.width, self.height)

    def describe(self) -> str:
        size = f"{self.width}x{self.height}, fx {self.k[0, 0]:.2f} fy {self.k[1, 1]:.2f}"
        if not self.distorted:
            return f"{size}, no distortion"
        return (f"{size}, {self.model} distortion {np.round(self.distortion, 5).tolist()} removed "
                f"(images undistorted onto P: fx {self.p[0, 0]:.2f} fy {self.p[1, 1]:.2f})")

    def undistortion_maps(self) -> tuple[np.ndarray, np.ndarray] | None:
        """OpenCV remap tables from rectified pixels to recorded ones, or None without distortion."""
        if not self.distorted:
            return None
        return cv2.initUndistortRectifyMap(self.k, self.distortion, None, self.p, (self.width, self.height),
                                           cv2.CV_32FC1)


def _check_full_frame(message: object, width: int, height: int) -> None:
    """Binned or cropped images would need K changed; the reader takes only full-resolution, uncropped ones."""
    binning = (int(message.binning_x), int(message.binning_y))  # type: ignore[attr-defined]
    roi = message.roi  # type: ignore[attr-defined]
    window = (int(roi.x_offset), int(roi.y_offset), int(roi.width), int(roi.height))
    if any(b > 1 for b in binning):
        raise ValueError(f"CameraInfo binning {binning[0]}x{binning[1]} is not supported; record unbinned images")
    if window[2:] != (0, 0) and window != (0, 0, width, height):
        raise ValueError(f"CameraInfo region of interest {window} (x, y, width, height) is not supported; "
                         "record full images")


def check_size(calibration: Calibration, width: int, height: int, whose: str = "") -> None:
    """ValueError unless an image of ``width`` x ``height`` has the size its CameraInfo (described by
    ``whose``) gives."""
    if (width, height) != (calibration.width, calibration.height):
        raise ValueError(f"image is {width}x{height} but its CameraInfo{whose} says "
                         f"{calibration.width}x{calibration.height}")


def undistort(image: np.ndarray, maps: tuple[np.ndarray, np.ndarray] | None, nearest: bool) -> np.ndarray:
    """The image resampled through ``maps`` (nearest for depth, bilinear for colour); as is without."""
    if maps is None:
        return image
    interpolation = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    return cv2.remap(image, maps[0], maps[1], interpolation, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
