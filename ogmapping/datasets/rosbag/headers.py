"""A message's ``std_msgs/Header`` read straight from its serialized bytes.

Images, camera infos and poses all begin with a header. Indexing a bag needs every image's stamp
and frame; reading them from the first bytes avoids decoding (and copying) each image twice.
ROS 1 lays out ``uint32 seq, uint32 secs, uint32 nsecs, string frame_id`` little-endian; ROS 2 CDR
starts with a 4-byte encapsulation header (its second byte 1 for little-endian, 0 for big) and then
``int32 sec, uint32 nanosec, string frame_id`` (the length counts a trailing NUL).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass


@dataclass(frozen=True)
class Header:
    stamp_ns: int
    frame_id: str


def normalise_frame(frame_id: str) -> str:
    """TF frame names without ROS 1's leading slash, so ``/camera`` and ``camera`` are one frame."""
    return frame_id.lstrip("/")


def read_header(raw: bytes | memoryview, ros2: bool) -> Header:
    """The header at the start of a serialized message; ValueError if the bytes are too short for one."""
    data = bytes(raw[:1024])
    try:
        if ros2:
            order = "<" if data[1] == 1 else ">"
            sec, nanosec, length = struct.unpack_from(order + "iII", data, 4)
            name = data[16 : 16 + length].rstrip(b"\0")
        else:
            sec, nanosec, length = struct.unpack_from("<xxxxIII", data, 0)
            name = data[16 : 16 + length]
    except (struct.error, IndexError) as error:
        raise ValueError(f"message too short for a std_msgs/Header ({len(raw)} bytes)") from error
    return Header(sec * 1_000_000_000 + nanosec, normalise_frame(name.decode("utf-8", errors="replace")))


def stamp_ns(stamp: object) -> int:
    """Nanoseconds of a decoded ``builtin_interfaces/Time``."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)  # type: ignore[attr-defined]
