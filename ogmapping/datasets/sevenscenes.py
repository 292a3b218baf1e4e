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

Where the recording stored a capture twice (``repeats="retimed"``, default), each image is seen from the pose
of its own time (``ogmapping.datasets.repeats``); ``"as-recorded"`` keeps the files' poses.

Pixel convention: every K here, the file's and the measured one, was used with integer pixel
centres (the measurement was made relative to the file's K, with the file's tools), so both get
+0.5 on cx and cy. Shifting both keeps the measured colour/depth relation exact and keeps the
same rays that every other tool casts from this data; the shift is half a pixel (about 2 mm at 2 m).
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np

from ogmapping.datasets.base import (
    FileSource,
    FrameFiles,
    IntrinsicsOption,
    explicit_intrinsics,
    image_size,
    matrix_intrinsics,
    opencv_intrinsics,
)
from ogmapping.datasets.repeats import colour_time_pose
from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.frame import Frame

DEPTH_PATTERN = re.compile(r"^frame-(\d+)\.depth\.png$")
DEFAULT_DEPTH_K = (585.0, 585.0, 320.0, 240.0)
MEASURED_COLOR_K = (526.5, 526.5, 321.625, 238.125)
MEASURED_BASELINE = 0.0281  # metres: the colour camera sits this far along the depth camera's +x axis
MEASURED_SIZE = (640, 480)
COLOR_SUFFIXES = (".color.png", ".color.jpg")
REPEATS = ("retimed", "as-recorded")  # a capture stored twice seen from the pose of its time, or as the files say


def find_root(path: Path) -> Path | None:
    """The folder holding the frames: ``path`` itself or its ``data`` subfolder."""
    for candidate in (path, path / "data"):
        if candidate.is_dir() and any(DEPTH_PATTERN.match(p.name) for p in candidate.iterdir()):
            return candidate
    return None


class SevenScenes(FileSource):
    """Reader for one 7-Scenes sequence folder (or a folder with it under ``data/``)."""

    def __init__(self, path: str | Path, color_intrinsics: str | IntrinsicsOption = "measured",
                 depth_scale: float = 1000.0, fps: float = 30.0, repeats: str = "retimed") -> None:
        root = find_root(Path(path))
        if root is None:
            raise ValueError(f"no 7-Scenes frames (frame-*.depth.png) in {path} or {Path(path) / 'data'}")
        super().__init__("7scenes", root, depth_scale)
        if repeats not in REPEATS:
            raise ValueError(f"repeats must be one of {', '.join(REPEATS)}, got {repeats!r}")
        self.fps = fps
        self.retime_repeats = repeats == "retimed"
        self._files = self._scan(root, fps)
        if not self._files:
            raise ValueError(f"no complete 7-Scenes frame (colour + depth + pose) in {root}")

        first = self._files[0]
        depth_w, depth_h = image_size(first.depth)
        color_w, color_h = image_size(first.color)
        k_file = root / "camera-intrinsics.txt"
        if k_file.exists():
            self.depth_intrinsics = matrix_intrinsics(k_file, (3, 3), depth_w, depth_h)
        else:
            self.depth_intrinsics = opencv_intrinsics(*DEFAULT_DEPTH_K, depth_w, depth_h)
        self.color_intrinsics, self.depth_to_color = self._resolve_color(color_intrinsics, color_w, color_h)
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
    def _scan(root: Path, fps: float) -> list[FrameFiles]:
        """The complete frames in ``root`` by frame number; poses stay in their files until a frame loads."""
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
            entries.append((int(match.group(1)), stem, color))
        return [FrameFiles(root / color, root / (stem + ".depth.png"), root / (stem + ".pose.txt"), number / fps)
                for number, stem, color in sorted(entries, key=lambda e: e[0])]

    def _pose(self, files: FrameFiles) -> np.ndarray:
        """The colour camera's pose: the files hold the depth camera's."""
        depth_c2w = super()._pose(files)
        return depth_c2w if self._color_to_depth is None else depth_c2w @ self._color_to_depth

    def _load(self, position: int) -> Frame:
        """The frame, its colour image seen from the pose of its own time where a capture repeats (``repeats``)."""
        frame = super()._load(position)
        if not self.retime_repeats:
            return frame
        colour_pose = colour_time_pose(
            position, self._files, lambda p: FileSource._pose(self, self._files[p]), self._follows_directly,
        )
        if colour_pose is None:
            return frame
        depth_to_color = np.eye(4) if self.depth_to_color is None else self.depth_to_color
        depth_c2w = frame.c2w @ depth_to_color  # the files' pose, as read for the frame
        return dataclasses.replace(
            frame, c2w=colour_pose @ np.linalg.inv(depth_to_color),
            depth_to_color=depth_to_color @ np.linalg.inv(colour_pose) @ depth_c2w,
        )

    def _follows_directly(self, position: int) -> bool:
        """True when the frame at ``position`` is the one numbered right after the frame before it."""
        numbers = [int(DEPTH_PATTERN.match(self._files[p].depth.name).group(1)) for p in (position - 1, position)]
        return numbers[1] == numbers[0] + 1
