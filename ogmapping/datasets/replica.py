"""Replica renderings in the NICE-SLAM layout: ``results/frame*.jpg``, ``results/depth*.png``, ``traj.txt``.

``traj.txt`` holds one camera-to-world pose per line as 16 row-major numbers (OpenCV axes), in
frame order. Depth is uint16 at 6553.5 units per metre. The published K (600, 600, 599.5, 339.5
at 1200x680) puts the principal point at (W-1)/2, (H-1)/2, i.e. integer pixel centres; +0.5 makes
it the exact image centre in our convention. The renderer's colour and depth share one camera.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ogmapping.datasets.base import FileSource, FrameFiles, IntrinsicsOption, opencv_intrinsics, resolve_intrinsics

REPLICA_K = (600.0, 600.0, 599.5, 339.5)
REPLICA_SIZE = (1200, 680)
COLOR_PATTERN = re.compile(r"^frame(\d+)\.(jpg|png)$")
DEPTH_PATTERN = re.compile(r"^depth(\d+)\.png$")


def numbered(folder: Path, pattern: re.Pattern[str]) -> dict[int, Path]:
    """Files of ``folder`` matching ``pattern``, keyed by the number in their name."""
    found = {}
    for path in folder.iterdir():
        match = pattern.match(path.name)
        if match:
            found[int(match.group(1))] = path
    return found


def is_replica(path: Path) -> bool:
    results = path / "results"
    return (path / "traj.txt").is_file() and results.is_dir() and bool(numbered(results, DEPTH_PATTERN))


class Replica(FileSource):
    """Reader for one Replica scene folder (the one holding ``results/`` and ``traj.txt``)."""

    def __init__(self, path: str | Path, intrinsics: IntrinsicsOption = None, depth_scale: float = 6553.5,
                 fps: float = 30.0) -> None:
        root = Path(path)
        if not is_replica(root):
            raise ValueError(f"no Replica scene in {root}: expected traj.txt and results/depth*.png")
        super().__init__("replica", root, depth_scale)
        self.fps = fps

        colors = numbered(root / "results", COLOR_PATTERN)
        depths = numbered(root / "results", DEPTH_PATTERN)
        numbers = sorted(set(colors) & set(depths))
        if not numbers:
            raise ValueError(f"Replica scene {root}: no frame has both frame*.jpg and depth*.png")

        values = np.loadtxt(root / "traj.txt", dtype=np.float64, ndmin=2)
        if values.shape[1] != 16:
            raise ValueError(f"{root / 'traj.txt'}: expected 16 numbers per line, got {values.shape[1]}")
        if numbers[-1] >= len(values):
            raise ValueError(f"{root / 'traj.txt'} has {len(values)} poses but frames run to number {numbers[-1]}")
        poses = values[numbers].reshape(-1, 4, 4)
        self._files = [FrameFiles(colors[n], depths[n], pose, n / fps) for n, pose in zip(numbers, poses, strict=True)]

        published = opencv_intrinsics(*REPLICA_K, *REPLICA_SIZE).resized
        self.color_intrinsics = self.depth_intrinsics = resolve_intrinsics(intrinsics, published, colors[numbers[0]])
