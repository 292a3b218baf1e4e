"""Dataset readers behind one entry point, ``open_dataset``, which can tell the layouts apart itself."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ogmapping.datasets.base import FrameSource
from ogmapping.datasets.replica import Replica, is_replica
from ogmapping.datasets.rosbag import is_bag
from ogmapping.datasets.scannet import ScanNet, is_scannet
from ogmapping.datasets.sevenscenes import SevenScenes, find_root
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.datasets.tum import TUM, is_tum

FORMATS = ("auto", "7scenes", "tum", "replica", "scannet", "synthetic", "bag")

LOOKED_FOR = (
    "7scenes: frame-*.depth.png in the folder or its data/ subfolder; "
    "tum: rgb.txt and depth.txt; "
    "replica: traj.txt and results/depth*.png; "
    "scannet: color/, depth/, pose/ and intrinsic/ folders; "
    "bag: a ROS 1 .bag, a ROS 2 .mcap or .db3, or a ROS 2 bag folder with metadata.yaml"
)

__all__ = ["FORMATS", "TUM", "FrameSource", "Replica", "ScanNet", "SevenScenes", "SyntheticSource", "detect_format",
           "is_bag", "open_bag", "open_dataset"]


def detect_format(path: str | Path) -> str:
    """The format whose folder layout ``path`` has, or ValueError naming what was looked for."""
    if str(path) in ("", "synthetic"):
        return "synthetic"
    root = Path(path)
    if not root.exists():
        raise ValueError(f"dataset path does not exist: {root}")
    if is_bag(root):
        return "bag"
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
    ``format="bag"`` takes the fields of ``rosbag.topics.BagOptions`` and needs the ``robots`` extra.
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
    if format == "bag":
        return open_bag(root, **options)
    readers: dict[str, type[FrameSource]] = {
        "7scenes": SevenScenes, "tum": TUM, "replica": Replica, "scannet": ScanNet,
    }
    return readers[format](root, **options)


def open_bag(path: Path, **options: Any) -> FrameSource:
    """A ROS bag, with ``rosbags`` imported only now (the ``robots`` extra)."""
    try:
        from ogmapping.datasets.rosbag.source import RosBag
    except ImportError as error:
        raise ValueError(f"reading ROS bags needs the rosbags package: pip install 'ogmapping[robots]' ({error})") \
            from error
    return RosBag(path, **options)
