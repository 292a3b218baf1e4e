"""Engine types to API messages (the client's direction; the server validates the way back)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ogapi.images import encode_color, encode_depth
from ogapi.v1 import mapping_pb2 as pb
from ogmapping.camera import Intrinsics
from ogmapping.frame import Frame


@dataclass(frozen=True)
class FrameEncoding:
    """How a client packs frames; PNG colour and millimetre PNG depth lose nothing for 8-bit/mm data."""

    color: int = pb.COLOR_PNG
    depth: int = pb.DEPTH_PNG16
    depth_scale: float = 1000.0
    jpeg_quality: int = 95


def intrinsics_to_proto(intrinsics: Intrinsics) -> pb.CameraIntrinsics:
    return pb.CameraIntrinsics(
        fx=intrinsics.fx, fy=intrinsics.fy, cx=intrinsics.cx, cy=intrinsics.cy,
        width=intrinsics.width, height=intrinsics.height,
    )


def matrix_to_list(matrix: np.ndarray) -> list[float]:
    """4x4 matrix as 16 row-major numbers."""
    return [float(v) for v in np.asarray(matrix, dtype=np.float64).reshape(16)]


def frame_to_proto(frame: Frame, encoding: FrameEncoding = FrameEncoding()) -> pb.Frame:
    """An engine Frame as the message StreamFrames expects."""
    message = pb.Frame(
        index=frame.index,
        color=pb.ColorImage(
            encoding=encoding.color, data=encode_color(frame.rgb, encoding.color, encoding.jpeg_quality)
        ),
        depth=pb.DepthImage(
            encoding=encoding.depth,
            data=encode_depth(frame.depth, encoding.depth, encoding.depth_scale),
            depth_scale=encoding.depth_scale if encoding.depth == pb.DEPTH_PNG16 else 0.0,
        ),
        color_intrinsics=intrinsics_to_proto(frame.color_intrinsics),
        c2w=matrix_to_list(frame.c2w),
    )
    if frame.timestamp is not None:
        message.timestamp = frame.timestamp
    if frame.depth_intrinsics != frame.color_intrinsics:
        message.depth_intrinsics.CopyFrom(intrinsics_to_proto(frame.depth_intrinsics))
    if frame.depth_to_color is not None:
        message.depth_to_color.extend(matrix_to_list(frame.depth_to_color))
    return message
