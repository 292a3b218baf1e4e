"""Dataset readers behind one entry point, ``open_dataset``, which can tell the layouts apart itself."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ogmapping.datasets.base import FrameSource
from ogmapping.datasets.locate import locate
from ogmapping.datasets.replica import Replica
from ogmapping.datasets.rosbag import is_bag
from ogmapping.datasets.scannet import ScanNet
from ogmapping.datasets.sevenscenes import SevenScenes
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.datasets.tum import TUM

FORMATS = ("auto", "7scenes", "tum", "replica", "scannet", "synthetic", "bag")

LOOKED_FOR = (
    "in the folder, its data/ subfolder or one other subfolder: "
    "7scenes: frame-*.depth.png; "
    "tum: rgb.txt and depth.txt; "
    "replica: traj.txt and results/depth*.png; "
    "scannet: color/, depth/, pose/ and intrinsic/ folders; "
    "bag: a ROS 1 .bag, a ROS 2 .mcap or .db3, or a ROS 2 bag folder with metadata.yaml"
)

__all__ = ["FORMATS", "TUM", "FrameSource", "Replica", "ScanNet", "SevenScenes", "SyntheticSource", "detect_format",
           "find_dataset", "is_bag", "open_bag", "open_dataset"]


def detect_format(path: str | Path) -> str:
    """The format whose folder layout ``path`` has, or ValueError naming what was looked for."""
    return find_dataset(path)[0]


def find_dataset(path: str | Path, format: str = "auto") -> tuple[str, Path]:
    """The format of the dataset at ``path`` (``format``'s layout only, unless auto) and the folder holding it:
    ``path`` itself, or below it (``locate``); ValueError naming what was looked for where there is none."""
    if format == "synthetic" or (format == "auto" and str(path) in ("", "synthetic")):
        return "synthetic", Path(path)
    root = Path(path)
    if not root.exists():
        raise ValueError(f"dataset path does not exist: {root}")
    if format == "bag" or (format == "auto" and is_bag(root)):
        return "bag", root
    if not root.is_dir():
        raise ValueError(f"dataset path is not a folder: {root}")
    found = locate(root, format)
    if found is not None:
        return found
    if format != "auto":
        return format, root  # its reader says what it is missing
    raise ValueError(f"no known dataset layout in {root}; looked for {LOOKED_FOR}")


def open_dataset(path: str, format: str = "auto", **options: Any) -> FrameSource:
    """Open the sequence at ``path`` as a FrameSource; ``options`` go to the reader.

    ``format="synthetic"`` (or path ``"synthetic"`` / ``""`` with auto) needs no files; its
    options are ``n_frames`` (100), ``width`` (320), ``height`` (240) and ``seed`` (0).
    ``format="bag"`` takes the fields of ``rosbag.topics.BagOptions`` and needs the ``robots`` extra.
    """
    if format not in FORMATS:
        raise ValueError(f"unknown dataset format {format!r}; expected one of {', '.join(FORMATS)}")
    format, root = find_dataset(path, format)
    if format == "synthetic":
        return SyntheticSource(**options)
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
