"""Broken variants of a good frame, with the status code and field name each must be refused with.

Shared by the unit test of the validation module and the integration test through a server.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import grpc
import numpy as np
from ogapi.images import encode_color
from ogapi.v1 import mapping_pb2 as pb

INVALID, EXHAUSTED = grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.RESOURCE_EXHAUSTED
Change = Callable[[pb.Frame], object]


def broken(good: pb.Frame, change: Change) -> pb.Frame:
    message = pb.Frame()
    message.CopyFrom(good)
    change(message)
    return message


def set_c2w(values: list[float]) -> Change:
    def change(message: pb.Frame) -> None:
        del message.c2w[:]
        message.c2w.extend(values)
    return change


def set_color(encoding: int, data: bytes) -> Change:
    def change(message: pb.Frame) -> None:
        message.color.encoding = encoding
        message.color.data = data
    return change


SCALED = np.diag([1.2, 1.0, 1.0, 1.0]).reshape(-1).tolist()
REFLECTION = np.diag([-1.0, 1.0, 1.0, 1.0]).reshape(-1).tolist()
BAD_LAST_ROW = [*np.eye(4).reshape(-1)[:12].tolist(), 0.0, 0.0, 1.0, 1.0]
OTHER_CAMERA = pb.CameraIntrinsics(fx=50, fy=50, cx=20, cy=15, width=40, height=30)
# A depth camera the colour camera (80x60, fx 69) samples 30x as densely: registration's work grew with the square.
SPARSE_DEPTH_CAMERA = pb.CameraIntrinsics(fx=2.3, fy=2.3, cx=40, cy=30, width=80, height=60)
FAR_AWAY = [1.0, 0.0, 0.0, 7000.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0]  # beyond the octree

CASES: dict[str, tuple[Change, grpc.StatusCode, str]] = {
    "c2w wrong length": (set_c2w([1.0] * 12), INVALID, "c2w"),
    "c2w last row": (set_c2w(BAD_LAST_ROW), INVALID, "c2w"),
    "c2w not orthonormal": (set_c2w(SCALED), INVALID, "orthonormal"),
    "c2w reflection": (set_c2w(REFLECTION), INVALID, "reflection"),
    "c2w NaN": (set_c2w([math.nan] * 16), INVALID, "c2w"),
    "timestamp inf": (lambda m: setattr(m, "timestamp", math.inf), INVALID, "timestamp"),
    "timestamp negative": (lambda m: setattr(m, "timestamp", -1.0), INVALID, "timestamp"),
    "timestamp past uint64 ns": (lambda m: setattr(m, "timestamp", 2e10), INVALID, "timestamp"),
    "timestamp past protobuf Timestamp": (lambda m: setattr(m, "timestamp", 1e12), INVALID, "timestamp"),
    "fx NaN": (lambda m: setattr(m.color_intrinsics, "fx", math.nan), INVALID, "color_intrinsics.fx"),
    "fy negative": (lambda m: setattr(m.color_intrinsics, "fy", -5.0), INVALID, "color_intrinsics.fy"),
    "zero width": (lambda m: setattr(m.color_intrinsics, "width", 0), INVALID, "color_intrinsics"),
    "no intrinsics": (lambda m: m.ClearField("color_intrinsics"), INVALID, "color_intrinsics"),
    "wrong image size": (lambda m: setattr(m.color_intrinsics, "width", 40), INVALID, "color"),
    "too large image": (lambda m: setattr(m.color_intrinsics, "width", 4000), EXHAUSTED, "color_intrinsics"),
    "undecodable jpeg": (set_color(pb.COLOR_JPEG, b"\xff\xd8\xff\xdb\x00\x43garbage"), INVALID, "color"),
    "png labelled jpeg": (lambda m: setattr(m.color, "encoding", pb.COLOR_JPEG), INVALID, "color"),
    "raw colour wrong length": (set_color(pb.COLOR_RAW_RGB8, b"\x00" * 100), INVALID, "color"),
    "unknown colour encoding": (lambda m: setattr(m.color, "encoding", 17), INVALID, "color.encoding"),
    "empty colour": (lambda m: setattr(m.color, "data", b""), INVALID, "color.data"),
    "no depth": (lambda m: m.ClearField("depth"), INVALID, "depth"),
    "depth scale zero": (lambda m: setattr(m.depth, "depth_scale", 0.0), INVALID, "depth.depth_scale"),
    "depth scale negative": (lambda m: setattr(m.depth, "depth_scale", -1000.0), INVALID, "depth.depth_scale"),
    "depth scale NaN": (lambda m: setattr(m.depth, "depth_scale", math.nan), INVALID, "depth.depth_scale"),
    "depth scale below float32": (lambda m: setattr(m.depth, "depth_scale", 1e-300), INVALID, "depth.depth_scale"),
    "depth is 8-bit colour": (
        lambda m: setattr(m.depth, "data", encode_color(np.zeros((60, 80, 3)), pb.COLOR_PNG)), INVALID, "depth"
    ),
    "depth intrinsics mismatch": (lambda m: m.depth_intrinsics.CopyFrom(OTHER_CAMERA), INVALID, "depth"),
    "bad depth_to_color": (lambda m: m.depth_to_color.extend([2.0] * 16), INVALID, "depth_to_color"),
    "fx 1e300": (lambda m: setattr(m.color_intrinsics, "fx", 1e300), INVALID, "color_intrinsics.fx"),
    "fy tiny": (lambda m: setattr(m.color_intrinsics, "fy", 1e-300), INVALID, "color_intrinsics.fy"),
    "cx 1e300": (lambda m: setattr(m.color_intrinsics, "cx", 1e300), INVALID, "color_intrinsics.cx"),
    "depth camera 30x sparser": (lambda m: m.depth_intrinsics.CopyFrom(SPARSE_DEPTH_CAMERA), INVALID,
                                 "depth_intrinsics.fx"),
    "pose 7 km from the origin": (set_c2w(FAR_AWAY), INVALID, "c2w"),
}
