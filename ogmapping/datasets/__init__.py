"""Dataset readers behind one entry point, ``open_dataset``, which can tell the layouts apart itself."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ogmapping.datasets.base import FrameSource
from ogmapping.datasets.replica import Replica, is_replica
from ogmapping.datasets.scannet import ScanNet, is_scannet
from ogmapping.datasets.sevenscenes import SevenScenes, find_root
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.datasets.tum import TUM, is_tum

FORMATS = ("auto", "7scenes", "tum", "replica", "scannet", "synthetic")

LOOKED_FOR = (
    "7scenes: frame-*.depth.png in the folder or its data/ subfolder; "
    "tum: rgb.txt and depth.txt; "
    "replica: traj.txt and results/depth*.png; "
    "scannet: color/, depth/, pose/ and intrinsic/ folders"
)

__all__ = ["FORMATS", "TUM", "FrameSource", "Replica", "ScanNet", "SevenScenes", "SyntheticSource", "detect_format",
           "open_dataset"]


def detect_format(path: str | Path) -> str:
    """The format whose folder layout ``path`` has, or ValueError naming what was looked for."""
    if str(path) in ("", "synthetic"):
        return "synthetic"
    root = Path(path)
    if not root.exists():
        raise ValueError(f"dataset path does not exist: {root}")
    if not root.is_dir():
        raise ValueError(f"dataset path is not a folder: {root}")
    checks = (("tum", is_tum), ("scannet", is_scannet), ("replica", is_replica),
              ("7scenes", lambda p: find_root(p) is not None))
    for name, check in checks:
        if check(root):
            return name
    raise ValueError(f"no known dataset layout in {root}; looked for {LOOKED_FOR}")


def open_dataset(path: str, format: str = "auto", **options: Any) -> FrameSource:
    """Open the sequence at ``path`` as a FrameSource; ``options`` go to the reader.

    ``format="synthetic"`` (or path ``"synthetic"`` / ``""`` with auto) needs no files; its
    options are ``n_frames`` (100), ``width`` (320), ``height`` (240) and ``seed`` (0).
    """
    if format not in FORMATS:
        raise ValueError(f"unknown dataset format {format!r}; expected one of {', '.join(FORMATS)}")
    if format == "auto":
        format = detect_format(path)
    if format == "synthetic":
        return SyntheticSource(**options)
    root = Path(path)
    if not root.exists():
        raise ValueError(f"dataset path does not exist: {root}")
    readers: dict[str, type[FrameSource]] = {
        "7scenes": SevenScenes, "tum": TUM, "replica": Replica, "scannet": ScanNet,
    }
    return readers[format](root, **options)
