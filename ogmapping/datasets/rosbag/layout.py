"""Telling a bag from a dataset folder by its path alone, so detection needs no ``rosbags``."""

from __future__ import annotations

from pathlib import Path

ROS1_SUFFIX = ".bag"
ROS2_FILE_SUFFIXES = (".mcap", ".db3")


def is_bag(path: str | Path) -> bool:
    """A ROS 1 ``.bag`` file, a ROS 2 storage file (``.mcap``, ``.db3``) or a ROS 2 bag folder."""
    path = Path(path)
    if path.is_file():
        return path.suffix in (ROS1_SUFFIX, *ROS2_FILE_SUFFIXES)
    return path.is_dir() and (path / "metadata.yaml").is_file()
