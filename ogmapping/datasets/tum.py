"""TUM RGB-D sequences: ``rgb.txt``, ``depth.txt`` and ``groundtruth.txt`` beside the image folders.

The three streams run on separate clocks, so frames are built by association: each colour image
is paired with the nearest unused depth image and the nearest pose, both within ``max_dt``
seconds; colour images without both are dropped. Depth is uint16 at 5000 units per metre and is
registered to colour by the sensor driver. Default K is the freiburg1 calibration (517.3, 516.5,
318.6, 255.3), published with integer pixel centres and shifted by +0.5 to our convention;
pass ``intrinsics`` for the other sensors.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ogmapping.datasets.base import FileSource, FrameFiles, IntrinsicsOption, opencv_intrinsics, resolve_intrinsics
from ogmapping.frames.rotation import quaternion_pose

FR1_K = (517.3, 516.5, 318.6, 255.3)
MAX_DT = 0.02
LIST_FILES = ("rgb.txt", "depth.txt")


def is_tum(path: Path) -> bool:
    return all((path / name).is_file() for name in LIST_FILES)


def read_list(path: Path, columns: int) -> tuple[np.ndarray, list[list[str]]]:
    """Timestamps and remaining fields of a TUM list file, comments and blank lines skipped."""
    stamps, rows = [], []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        fields = line.replace(",", " ").split()
        if not fields or fields[0].startswith("#"):
            continue
        if len(fields) != columns:
            raise ValueError(f"{path}:{number}: expected {columns} fields, got {len(fields)}")
        stamps.append(float(fields[0]))
        rows.append(fields[1:])
    return np.asarray(stamps, dtype=np.float64), rows


def nearest(query: np.ndarray, stamps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index of the nearest entry of sorted ``stamps`` for each query, and the time gap."""
    right = np.clip(np.searchsorted(stamps, query), 1, len(stamps) - 1)
    left = right - 1
    pick = np.where(np.abs(query - stamps[left]) <= np.abs(stamps[right] - query), left, right)
    return pick, np.abs(stamps[pick] - query)


def associate_unique(a: np.ndarray, b: np.ndarray, max_dt: float) -> list[tuple[int, int]]:
    """One-to-one pairs (i, j) with |a_i - b_j| < max_dt, closest pairs chosen first."""
    order = np.argsort(b, kind="stable")
    sorted_b = b[order]
    right = np.searchsorted(sorted_b, a)
    candidates = []
    for i, r in enumerate(right):
        for j in (r - 1, r):
            if 0 <= j < len(sorted_b) and abs(a[i] - sorted_b[j]) < max_dt:
                candidates.append((abs(a[i] - sorted_b[j]), i, int(order[j])))
    used_a, used_b, pairs = set(), set(), []
    for _, i, j in sorted(candidates):
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            pairs.append((i, j))
    return sorted(pairs)


class TUM(FileSource):
    """Reader for one TUM RGB-D sequence folder."""

    def __init__(self, path: str | Path, intrinsics: IntrinsicsOption = None, depth_scale: float = 5000.0,
                 max_dt: float = MAX_DT) -> None:
        root = Path(path)
        if not is_tum(root):
            raise ValueError(f"no TUM RGB-D sequence in {root}: expected rgb.txt and depth.txt")
        ground_truth = root / "groundtruth.txt"
        if not ground_truth.is_file():
            raise ValueError(f"TUM sequence {root} has no groundtruth.txt; poses are required")
        super().__init__("tum", root, depth_scale)

        rgb_t, rgb_rows = read_list(root / "rgb.txt", 2)
        depth_t, depth_rows = read_list(root / "depth.txt", 2)
        pose_t, pose_rows = read_list(ground_truth, 8)
        if len(rgb_t) == 0 or len(depth_t) == 0 or len(pose_t) < 2:
            raise ValueError(f"TUM sequence {root} lists too few images or poses")
        pose_order = np.argsort(pose_t, kind="stable")
        pose_t = pose_t[pose_order]
        poses = np.asarray([pose_rows[i] for i in pose_order], dtype=np.float64)

        self._files = []
        for i, j in associate_unique(rgb_t, depth_t, max_dt):
            k, gap = nearest(rgb_t[i : i + 1], pose_t)
            if gap[0] >= max_dt:
                continue
            c2w = quaternion_pose(poses[k[0], :3], poses[k[0], 3:])  # tx ty tz, then qx qy qz qw
            self._files.append(FrameFiles(root / rgb_rows[i][0], root / depth_rows[j][0], c2w, float(rgb_t[i])))
        self._files.sort(key=lambda f: f.timestamp)
        if not self._files:
            raise ValueError(f"TUM sequence {root}: no colour image has depth and a pose within {max_dt} s")

        published = opencv_intrinsics(*FR1_K, 640, 480).resized
        self.color_intrinsics = self.depth_intrinsics = resolve_intrinsics(intrinsics, published, self._files[0].color)
