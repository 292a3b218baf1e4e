"""Telling a bag from a dataset folder by its path alone, so detection needs no ``rosbags``."""

from __future__ import annotations

from pathlib import Path

ROS1_SUFFIX = ".bag"
ROS2_FILE_SUFFIXES = (".mcap", ".db3")
METADATA = "metadata.yaml"
# How each storage file begins, and what it is called in a refusal.
SIGNATURES = {
    b"#ROSBAG V2.0\n": "a ROS 1 bag",
    b"\x89MCAP0\r\n": "an MCAP file",
    b"SQLite format 3\x00": "an SQLite database",
}


def is_bag(path: str | Path) -> bool:
    """A ROS 1 ``.bag`` file, a ROS 2 storage file (``.mcap``, ``.db3``) or a ROS 2 bag folder."""
    path = Path(path)
    if path.is_file():
        return path.suffix in (ROS1_SUFFIX, *ROS2_FILE_SUFFIXES)
    return path.is_dir() and (path / METADATA).is_file()


def check_signature(path: Path) -> None:
    """ValueError "not a ROS bag" for a file that does not begin as a ROS 1 bag, an MCAP file or an
    SQLite database does, or a folder without a text metadata.yaml (what rosbags would say of them is
    a decoding error from deep inside)."""
    if path.is_dir():
        metadata = path / METADATA
        if not metadata.is_file():
            raise ValueError(f"not a ROS bag: {path} is a folder without {METADATA}")
        try:
            metadata.read_bytes().decode("utf-8")
        except UnicodeDecodeError:
            raise ValueError(f"not a ROS bag: {metadata} is not text") from None
        return
    with open(path, "rb") as stream:
        head = stream.read(max(len(signature) for signature in SIGNATURES))
    if not head:
        raise ValueError(f"not a ROS bag: {path} is empty")
    if not any(head.startswith(signature) for signature in SIGNATURES):
        *others, last = SIGNATURES.values()
        raise ValueError(f"not a ROS bag: {path} does not begin as {', '.join(others)} or {last} does "
                         f"(it begins {head[:8]!r})")
