"""Microsoft 7-Scenes frames: ``frame-XXXXXX.{color.jpg|color.png, depth.png, pose.txt}``.

Depth is uint16 millimetres (0 and 65535 invalid), poses are camera-to-world in metres, and the
optional ``camera-intrinsics.txt`` is the depth camera's 3x3 K (585, 585, 320, 240 when absent).

The colour camera is another camera, beside the depth camera. ``color_intrinsics="measured"``
(default) models it as fx = fy = 526.5, cx = 321.625, cy = 238.125 at 640x480, 2.81 cm along the
depth camera's x axis: fitted by ``bench/colour_calibration.py`` so that the silhouettes of the
depth images land on colour edges (the Kinect's RGB-to-IR baseline is nominally 2.5 cm). Frames
then carry that offset as ``depth_to_color`` and the colour camera's pose as ``c2w`` (the files'
poses are the depth camera's), and ``ogmapping.frames.preprocess.register_depth`` re-projects
depth into the colour camera. An earlier fit without the baseline (528, 314.5, 238.5; SOURCE.md)
is right at about 1.8 m only: the parallax of a 2.8 cm baseline is 7.4 px at 2 m and 18 px at
0.8 m. ``"depth"`` reuses the depth camera for colour (registered frames, the files' poses);
explicit values give a colour camera at the depth camera's centre.

Pixel convention: every K here, the file's and the measured one, was used with integer pixel
centres (the measurement was made relative to the file's K, with the file's tools), so both get
+0.5 on cx and cy. Shifting both keeps the measured colour/depth relation exact and keeps the
same rays that every other tool casts from this data; the shift is half a pixel (about 2 mm at 2 m).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ogmapping.datasets.base import (
    FrameSource,
    IntrinsicsOption,
    explicit_intrinsics,
    image_size,
    opencv_intrinsics,
    read_depth,
    read_matrix,
    read_rgb,
)
from ogmapping.frames.camera import Intrinsics, validate_pose
from ogmapping.frames.frame import Frame

DEPTH_PATTERN = re.compile(r"^frame-(\d+)\.depth\.png$")
DEFAULT_DEPTH_K = (585.0, 585.0, 320.0, 240.0)
MEASURED_COLOR_K = (526.5, 526.5, 321.625, 238.125)
MEASURED_BASELINE = 0.0281  # metres: the colour camera sits this far along the depth camera's +x axis
MEASURED_SIZE = (640, 480)
COLOR_SUFFIXES = (".color.png", ".color.jpg")


@dataclass(frozen=True)
class _Entry:
    number: int
    color: Path
    depth: Path
    pose: Path


def find_root(path: Path) -> Path | None:
    """The folder holding the frames: ``path`` itself or its ``data`` subfolder."""
    for candidate in (path, path / "data"):
        if candidate.is_dir() and any(DEPTH_PATTERN.match(p.name) for p in candidate.iterdir()):
            return candidate
    return None


class SevenScenes(FrameSource):
    """Reader for one 7-Scenes sequence folder (or a folder with it under ``data/``)."""

    def __init__(
        self,
        path: str | Path,
        color_intrinsics: str | IntrinsicsOption = "measured",
        depth_scale: float = 1000.0,
        fps: float = 30.0,
    ) -> None:
        root = find_root(Path(path))
        if root is None:
            raise ValueError(f"no 7-Scenes frames (frame-*.depth.png) in {path} or {Path(path) / 'data'}")
        self.root = root
        self.name = f"7scenes:{root}"
        self.depth_scale = depth_scale
        self.fps = fps
        self._entries = self._scan(root)
        if not self._entries:
            raise ValueError(f"no complete 7-Scenes frame (colour + depth + pose) in {root}")

        first = self._entries[0]
        depth_w, depth_h = image_size(first.depth)
        color_w, color_h = image_size(first.color)
        k_file = root / "camera-intrinsics.txt"
        k = read_matrix(k_file, (3, 3)) if k_file.exists() else None
        depth_k = DEFAULT_DEPTH_K if k is None else (k[0, 0], k[1, 1], k[0, 2], k[1, 2])
        self.depth_intrinsics = opencv_intrinsics(*depth_k, depth_w, depth_h)
        # depth_to_color: colour-camera coordinates from depth-camera ones; None: the same optical centre.
        self._color_intrinsics, self.depth_to_color = self._resolve_color(color_intrinsics, color_w, color_h)
        self._color_to_depth = None if self.depth_to_color is None else np.linalg.inv(self.depth_to_color)

    def _resolve_color(
        self, option: str | IntrinsicsOption, width: int, height: int,
    ) -> tuple[Intrinsics, np.ndarray | None]:
        """The colour camera's intrinsics and its depth_to_color transform, for the option."""
        if not isinstance(option, str):
            return explicit_intrinsics(option, width, height), None
        if option == "depth":
            return self.depth_intrinsics.resized(width, height), None
        if option == "measured":
            depth_to_color = np.eye(4)
            depth_to_color[0, 3] = -MEASURED_BASELINE
            return opencv_intrinsics(*MEASURED_COLOR_K, *MEASURED_SIZE).resized(width, height), depth_to_color
        raise ValueError(f"color_intrinsics must be 'measured', 'depth' or explicit values, got {option!r}")

    @staticmethod
    def _scan(root: Path) -> list[_Entry]:
        names = {p.name for p in root.iterdir()}
        entries = []
        for name in names:
            match = DEPTH_PATTERN.match(name)
            if match is None:
                continue
            stem = name[: -len(".depth.png")]
            color = next((stem + s for s in COLOR_SUFFIXES if stem + s in names), None)
            if color is None or stem + ".pose.txt" not in names:
                continue
            entries.append(_Entry(int(match.group(1)), root / color, root / name, root / (stem + ".pose.txt")))
        return sorted(entries, key=lambda e: e.number)

    def __len__(self) -> int:
        return len(self._entries)

    @property
    def intrinsics(self) -> Intrinsics:
        return self._color_intrinsics

    def _load(self, position: int) -> Frame:
        entry = self._entries[position]
        depth_c2w = validate_pose(read_matrix(entry.pose, (4, 4)), name=str(entry.pose))
        c2w = depth_c2w if self._color_to_depth is None else depth_c2w @ self._color_to_depth
        return Frame(
            index=position,
            rgb=read_rgb(entry.color),
            depth=read_depth(entry.depth, self.depth_scale),
            color_intrinsics=self._color_intrinsics,
            depth_intrinsics=self.depth_intrinsics,
            c2w=c2w,
            timestamp=entry.number / self.fps,
            depth_to_color=None if self.depth_to_color is None else self.depth_to_color.copy(),
        )
