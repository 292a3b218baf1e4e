"""ScanNet scenes exported by its SensReader: ``color/N.jpg``, ``depth/N.png``, ``pose/N.txt``, ``intrinsic/``.

Colour (1296x968) and depth (640x480, uint16 millimetres) come from different cameras with their
own 4x4 ``intrinsic_color.txt`` / ``intrinsic_depth.txt``, so frames are unregistered; the exported
extrinsics are identity in practice and are not read (``depth_to_color`` None). Poses are
camera-to-world; ScanNet marks tracking failures with inf/nan poses, and those frames are left
out before positions are numbered. Intrinsics were calibrated with integer pixel centres and get
+0.5 on cx, cy for our convention.
"""

from __future__ import annotations

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
from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.frame import Frame

FOLDERS = ("color", "depth", "pose", "intrinsic")


def is_scannet(path: Path) -> bool:
    return all((path / name).is_dir() for name in FOLDERS)


def numbered(folder: Path, suffix: str) -> dict[int, Path]:
    """Files ``N<suffix>`` of ``folder`` keyed by N, so that 10 sorts after 9."""
    return {int(p.stem): p for p in folder.iterdir() if p.suffix == suffix and p.stem.isdigit()}


def _resolve(option: IntrinsicsOption, path: Path, width: int, height: int) -> Intrinsics:
    """The user's intrinsics if given, else the exported 4x4 file's."""
    if option is not None:
        return explicit_intrinsics(option, width, height)
    k = read_matrix(path, (4, 4))
    return opencv_intrinsics(k[0, 0], k[1, 1], k[0, 2], k[1, 2], width, height)


class ScanNet(FrameSource):
    """Reader for one exported ScanNet scene folder."""

    def __init__(
        self,
        path: str | Path,
        color_intrinsics: IntrinsicsOption = None,
        depth_intrinsics: IntrinsicsOption = None,
        depth_scale: float = 1000.0,
        fps: float = 30.0,
    ) -> None:
        root = Path(path)
        if not is_scannet(root):
            raise ValueError(f"no ScanNet export in {root}: expected folders {', '.join(FOLDERS)}")
        self.root = root
        self.name = f"scannet:{root}"
        self.depth_scale = depth_scale
        self.fps = fps

        colors = numbered(root / "color", ".jpg") or numbered(root / "color", ".png")
        depths = numbered(root / "depth", ".png")
        poses = numbered(root / "pose", ".txt")
        self._numbers: list[int] = []
        self._poses: list[np.ndarray] = []
        for number in sorted(set(colors) & set(depths) & set(poses)):
            pose = read_matrix(poses[number], (4, 4))
            if np.all(np.isfinite(pose)):
                self._numbers.append(number)
                self._poses.append(pose)
        if not self._numbers:
            raise ValueError(f"ScanNet export {root}: no frame has colour, depth and a finite pose")
        self._colors = [colors[n] for n in self._numbers]
        self._depths = [depths[n] for n in self._numbers]

        color_size = image_size(self._colors[0])
        depth_size = image_size(self._depths[0])
        self._color_intrinsics = _resolve(color_intrinsics, root / "intrinsic" / "intrinsic_color.txt", *color_size)
        self.depth_intrinsics = _resolve(depth_intrinsics, root / "intrinsic" / "intrinsic_depth.txt", *depth_size)

    def __len__(self) -> int:
        return len(self._numbers)

    @property
    def intrinsics(self) -> Intrinsics:
        return self._color_intrinsics

    def _load(self, position: int) -> Frame:
        return Frame(
            index=position,
            rgb=read_rgb(self._colors[position]),
            depth=read_depth(self._depths[position], self.depth_scale),
            color_intrinsics=self._color_intrinsics,
            depth_intrinsics=self.depth_intrinsics,
            c2w=self._poses[position].copy(),
            timestamp=self._numbers[position] / self.fps,
        )
