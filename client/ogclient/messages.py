"""Engine types to API messages, the client's direction (the server validates the way back).

Here rather than in ``ogapi`` so the API package never imports the engine.
"""

from __future__ import annotations

from collections.abc import Iterator

from ogapi.convert import FrameEncoding, matrix_to_list
from ogapi.images import encode_color, encode_depth
from ogapi.v1 import mapping_pb2 as pb

from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.frame import Frame

DEFAULT_ENCODING = FrameEncoding()  # lossless PNG colour, millimetre PNG depth
RESTORE_CHUNK_BYTES = 1 << 20


def restore_chunks(snapshot: bytes, label: str) -> Iterator[pb.RestoreChunk]:
    """A snapshot as the RestoreSession stream (at least one chunk; the label on the first)."""
    for offset in range(0, max(len(snapshot), 1), RESTORE_CHUNK_BYTES):
        yield pb.RestoreChunk(data=snapshot[offset:offset + RESTORE_CHUNK_BYTES], label=label if offset == 0 else "")


def intrinsics_to_proto(intrinsics: Intrinsics) -> pb.CameraIntrinsics:
    return pb.CameraIntrinsics(
        fx=intrinsics.fx, fy=intrinsics.fy, cx=intrinsics.cx, cy=intrinsics.cy,
        width=intrinsics.width, height=intrinsics.height,
    )


def frame_to_proto(frame: Frame, encoding: FrameEncoding = DEFAULT_ENCODING) -> pb.Frame:
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
