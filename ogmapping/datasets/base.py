"""What every dataset reader offers, and the image decoding they share.

Readers index frames by position in their own sorted frame list, never by the numbers in file
names, so that skipped or renumbered frames cannot shift poses against images.

Intrinsics files of the public datasets follow OpenCV's convention (pixel centres at integers);
``opencv_intrinsics`` moves them to ours (centres at +0.5, see ``ogmapping.frames.camera``) in one place.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator, Sequence
from pathlib import Path

import cv2
import numpy as np

from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.frame import Frame

# Sensors write these raw values where they have no measurement.
INVALID_RAW_DEPTH = (0, 65535)

IntrinsicsOption = Intrinsics | Sequence[float] | None


class FrameSource(ABC):
    """A finite, random-access sequence of frames."""

    name: str

    @abstractmethod
    def __len__(self) -> int: ...

    @abstractmethod
    def _load(self, position: int) -> Frame:
        """Frame at a position already checked to be in range."""

    @property
    @abstractmethod
    def intrinsics(self) -> Intrinsics:
        """Colour intrinsics at the native image size."""

    def report(self) -> list[str]:
        """What the reader chose or assumed that a user should see (a bag's topics and pose source)."""
        return []

    def __getitem__(self, position: int) -> Frame:
        count = len(self)
        if position < 0:
            position += count
        if not 0 <= position < count:
            raise IndexError(f"{self.name}: frame position {position} out of range (0..{count - 1})")
        return self._load(position)

    def __iter__(self) -> Iterator[Frame]:
        for position in range(len(self)):
            yield self._load(position)


def opencv_intrinsics(fx: float, fy: float, cx: float, cy: float, width: int, height: int) -> Intrinsics:
    """Our Intrinsics from values published with integer pixel centres (OpenCV, ROS, the datasets)."""
    return Intrinsics(float(fx), float(fy), float(cx) + 0.5, float(cy) + 0.5, int(width), int(height))


def explicit_intrinsics(option: Intrinsics | Sequence[float], width: int, height: int) -> Intrinsics:
    """Resolve intrinsics a user passed to a reader.

    An ``Intrinsics`` is taken as is (our convention); a 4-sequence (fx, fy, cx, cy) is read as a
    dataset's published numbers (OpenCV convention) at the native image size.
    """
    if isinstance(option, Intrinsics):
        return option
    values = [float(v) for v in option]
    if len(values) != 4:
        raise ValueError(f"intrinsics must be an Intrinsics or (fx, fy, cx, cy), got {option!r}")
    return opencv_intrinsics(*values, width, height)


def read_rgb(path: Path) -> np.ndarray:
    """Colour image as float32 (H, W, 3) in [0, 1]."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"cannot read colour image {path}")
    return opencv_to_rgb(image)


def opencv_to_rgb(image: np.ndarray) -> np.ndarray:
    """An image as OpenCV decodes it (grey, BGR or BGRA; 8 or 16 bit) as float32 RGB in [0, 1]."""
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    elif image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    else:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    scale = 1.0 / np.iinfo(image.dtype).max if image.dtype.kind == "u" else 1.0
    return np.clip(image.astype(np.float32) * np.float32(scale), 0.0, 1.0)


def read_depth(path: Path, depth_scale: float) -> np.ndarray:
    """Depth image in metres (float32) from a raw PNG holding ``depth_scale`` units per metre."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise ValueError(f"cannot read depth image {path}")
    if raw.ndim != 2:
        raise ValueError(f"depth image {path} has {raw.shape[2]} channels, expected one")
    return decode_depth(raw, depth_scale)


def decode_depth(raw: np.ndarray, depth_scale: float) -> np.ndarray:
    """Metres from raw sensor units, with every invalid marker turned into 0."""
    depth = raw.astype(np.float32) / np.float32(depth_scale)
    invalid = ~np.isfinite(depth) | (depth <= 0)
    if raw.dtype.kind in "ui":
        invalid |= np.isin(raw, INVALID_RAW_DEPTH)
    depth[invalid] = 0.0
    return depth


def image_size(path: Path) -> tuple[int, int]:
    """(width, height) of an image file, read once to fix a reader's intrinsics."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"cannot read image {path}")
    return int(image.shape[1]), int(image.shape[0])


def read_matrix(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """A whitespace-separated matrix file, checked for its shape."""
    try:
        values = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except ValueError as error:
        raise ValueError(f"cannot parse matrix file {path}: {error}") from error
    if values.shape != shape:
        raise ValueError(f"{path} holds a {values.shape} matrix, expected {shape}")
    return values
