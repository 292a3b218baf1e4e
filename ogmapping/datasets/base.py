"""What every dataset reader offers, and what they share: frames built from fixed cameras, frames
read from listed image files, image decoding.

Readers index frames by position in their own sorted frame list, never by the numbers in file
names, so that skipped or renumbered frames cannot shift poses against images. A reader of files
keeps only what is its own format: how it finds and pairs the files, poses and cameras when it opens.

Intrinsics files of the public datasets follow OpenCV's convention (pixel centres at integers);
``opencv_intrinsics`` moves them to ours (centres at +0.5, see ``ogmapping.frames.camera``) in one place.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ogmapping.frames.camera import Intrinsics, validate_pose
from ogmapping.frames.frame import Frame
from ogmapping.frames.trajectory import Trajectory

# Sensors write these raw values where they have no measurement.
INVALID_RAW_DEPTH = (0, 65535)

IntrinsicsOption = Intrinsics | Sequence[float] | None


class FrameSource(ABC):
    """A finite, random-access sequence of frames."""

    name: str
    corrected: Trajectory | None = None  # corrected poses the data carries for its frames (a bag's --corrected-topic)

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


class CameraSource(FrameSource):
    """A source whose cameras are fixed when it opens; every frame it builds carries them."""

    color_intrinsics: Intrinsics
    depth_intrinsics: Intrinsics
    depth_to_color: np.ndarray | None = None  # colour-camera coordinates from depth-camera ones; None: one centre

    @property
    def intrinsics(self) -> Intrinsics:
        return self.color_intrinsics

    def _frame(self, position: int, rgb: np.ndarray, depth: np.ndarray, c2w: np.ndarray, timestamp: float) -> Frame:
        """The frame at ``position``, with this source's cameras (``depth_to_color`` copied: frames own it)."""
        return Frame(
            index=position,
            rgb=rgb,
            depth=depth,
            color_intrinsics=self.color_intrinsics,
            depth_intrinsics=self.depth_intrinsics,
            c2w=c2w,
            timestamp=timestamp,
            depth_to_color=None if self.depth_to_color is None else self.depth_to_color.copy(),
        )


@dataclass(frozen=True)
class FrameFiles:
    """One frame on disk: its images, its camera-to-world (or the file to read it from when the frame
    loads, so opening a long sequence reads no pose file) and its time in seconds."""

    color: Path
    depth: Path
    pose: np.ndarray | Path
    timestamp: float


class FileSource(CameraSource):
    """A reader of the frames it lists when it opens (``_files``), depth at ``depth_scale`` units per metre."""

    _files: list[FrameFiles]

    def __init__(self, kind: str, root: Path, depth_scale: float) -> None:
        self.root = root
        self.name = f"{kind}:{root}"
        self.depth_scale = depth_scale

    def __len__(self) -> int:
        return len(self._files)

    def _load(self, position: int) -> Frame:
        files = self._files[position]
        c2w = self._pose(files)
        return self._frame(position, read_rgb(files.color), read_depth(files.depth, self.depth_scale), c2w,
                           files.timestamp)

    def _pose(self, files: FrameFiles) -> np.ndarray:
        """The frame's camera-to-world: a copy of the listed one, or its file's, checked."""
        if isinstance(files.pose, Path):
            return validate_pose(read_matrix(files.pose, (4, 4)), name=str(files.pose))
        return files.pose.copy()


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


def resolve_intrinsics(
    option: IntrinsicsOption, published: Callable[[int, int], Intrinsics], image: Path,
) -> Intrinsics:
    """The user's intrinsics if given, else the dataset's own at ``image``'s (width, height): a function
    of the size, so that a calibration file is read only when the user gave none."""
    width, height = image_size(image)
    if option is None:
        return published(width, height)
    return explicit_intrinsics(option, width, height)


def matrix_intrinsics(path: Path, shape: tuple[int, int], width: int, height: int) -> Intrinsics:
    """Intrinsics from a file holding K in the top left of a ``shape`` matrix (OpenCV convention)."""
    k = read_matrix(path, shape)
    return opencv_intrinsics(k[0, 0], k[1, 1], k[0, 2], k[1, 2], width, height)


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
