"""ScanNet scenes exported by its SensReader: ``color/N.jpg``, ``depth/N.png``, ``pose/N.txt``, ``intrinsic/``.

Colour (1296x968) and depth (640x480, uint16 millimetres) come from different cameras with their
own 4x4 ``intrinsic_color.txt`` / ``intrinsic_depth.txt``, so frames are unregistered; the exported
extrinsics are identity in practice and are not read (``depth_to_color`` None). Poses are
camera-to-world; ScanNet marks tracking failures with inf/nan poses, and those frames are left
out before positions are numbered. Intrinsics were calibrated with integer pixel centres and get
+0.5 on cx, cy for our convention.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path

import numpy as np

from ogmapping.datasets.base import (
    FileSource,
    FrameFiles,
    IntrinsicsOption,
    matrix_intrinsics,
    read_matrix,
    resolve_intrinsics,
)

FOLDERS = ("color", "depth", "pose", "intrinsic")


def is_scannet(path: Path) -> bool:
    return all((path / name).is_dir() for name in FOLDERS)


def numbered(folder: Path, suffix: str) -> dict[int, Path]:
    """Files ``N<suffix>`` of ``folder`` keyed by N, so that 10 sorts after 9."""
    return {int(p.stem): p for p in folder.iterdir() if p.suffix == suffix and p.stem.isdigit()}


class ScanNet(FileSource):
    """Reader for one exported ScanNet scene folder."""

    def __init__(self, path: str | Path, color_intrinsics: IntrinsicsOption = None,
                 depth_intrinsics: IntrinsicsOption = None, depth_scale: float = 1000.0, fps: float = 30.0) -> None:
        root = Path(path)
        if not is_scannet(root):
            raise ValueError(f"no ScanNet export in {root}: expected folders {', '.join(FOLDERS)}")
        super().__init__("scannet", root, depth_scale)
        self.fps = fps

        colors = numbered(root / "color", ".jpg") or numbered(root / "color", ".png")
        depths = numbered(root / "depth", ".png")
        poses = numbered(root / "pose", ".txt")
        self._files = []
        for number in sorted(set(colors) & set(depths) & set(poses)):
            pose = read_matrix(poses[number], (4, 4))
            if np.all(np.isfinite(pose)):
                self._files.append(FrameFiles(colors[number], depths[number], pose, number / fps))
        if not self._files:
            raise ValueError(f"ScanNet export {root}: no frame has colour, depth and a finite pose")

        first, calibration = self._files[0], root / "intrinsic"
        self.color_intrinsics = resolve_intrinsics(
            color_intrinsics, partial(matrix_intrinsics, calibration / "intrinsic_color.txt", (4, 4)), first.color)
        self.depth_intrinsics = resolve_intrinsics(
            depth_intrinsics, partial(matrix_intrinsics, calibration / "intrinsic_depth.txt", (4, 4)), first.depth)
