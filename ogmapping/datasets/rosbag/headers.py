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
    data = bytes(raw[:16])
    if len(data) < 16:
        raise ValueError(f"message too short for a std_msgs/Header ({len(raw)} bytes)")
    if ros2:  # the encapsulation's kind is even for big-endian (CDR_BE, PL_CDR_BE, ...), odd for little
        sec, nanosec, length = struct.unpack_from("<iII" if data[1] & 1 else ">iII", data, 4)
    else:
        sec, nanosec, length = struct.unpack_from("<III", data, 4)
    name = bytes(raw[16 : 16 + length])
    if len(name) < length:
        raise ValueError(f"message too short for its header's frame_id ({len(raw)} bytes, frame_id of {length})")
    return Header(sec * 1_000_000_000 + nanosec, normalise_frame(name.rstrip(b"\0").decode("utf-8", errors="replace")))


def stamp_ns(stamp: object) -> int:
    """Nanoseconds of a decoded ``builtin_interfaces/Time``."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)  # type: ignore[attr-defined]
