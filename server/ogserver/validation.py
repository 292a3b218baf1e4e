"""Turn untrusted messages into engine values, or refuse them naming the field.

Everything a client sends passes through here before it reaches a mapper or a recording, so a
refused frame leaves its session exactly as it was. Each refusal starts with the field's path in
the request message, spelled as the .proto spells it (``color_intrinsics.fx``, ``depth.encoding``),
and names enum values by their .proto names (``COLOR_PNG``): clients in any language map it back.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from ogapi.images import (
    COLOR_ENCODINGS,
    DEFAULT_JPEG_QUALITY,
    DEPTH_ENCODINGS,
    color_name,
    decode_color,
    decode_depth,
    depth_name,
)
from ogapi.v1 import mapping_pb2 as pb

from ogmapping.camera import Intrinsics, validate_pose
from ogmapping.frame import Frame
from ogserver.errors import exhausted, invalid

SESSION_ID_PATTERN = re.compile(r"[0-9a-f]{32}")
RECORDABLE_NANOSECONDS = 2**64  # exclusive
MAX_TIMESTAMP_SECONDS = RECORDABLE_NANOSECONDS / 1e9


def session_id(value: str, field: str = "session_id") -> str:
    """``field`` names where the id came from: a request's ``session_id`` or the ``x-session-id`` metadata."""
    if not value:
        raise invalid(field, "is required")
    if not SESSION_ID_PATTERN.fullmatch(value):
        raise invalid(field, f"must be 32 lowercase hex characters (got {value[:40]!r})")
    return value


def timestamp(message: pb.Frame) -> float | None:
    """Seconds, or None when absent; the recording stores them as MCAP's unsigned 64-bit nanoseconds."""
    if not message.HasField("timestamp"):
        return None
    seconds = float(message.timestamp)
    if not math.isfinite(seconds):
        raise invalid("timestamp", f"must be finite (got {seconds})")
    if not 0.0 <= seconds * 1e9 < RECORDABLE_NANOSECONDS:
        raise invalid("timestamp", f"must be from 0 up to {MAX_TIMESTAMP_SECONDS:.1f} seconds, what a recording's "
                                   f"unsigned 64-bit nanoseconds hold (got {seconds:g})")
    return seconds


def pose(values: Sequence[float], field: str) -> np.ndarray:
    """16 row-major numbers to a checked rigid 4x4 transform."""
    if len(values) != 16:
        raise invalid(field, f"must hold 16 numbers (a row-major 4x4 matrix), got {len(values)}")
    try:
        return validate_pose(np.asarray(values, dtype=np.float64).reshape(4, 4), field)
    except ValueError as error:
        raise invalid(field, str(error).removeprefix(f"{field} ")) from None


def intrinsics(message: pb.CameraIntrinsics, field: str, max_pixels: int) -> Intrinsics:
    """A camera that can exist, of a size within the server's limit."""
    for name in ("fx", "fy", "cx", "cy"):
        value = getattr(message, name)
        if not math.isfinite(value):
            raise invalid(f"{field}.{name}", f"must be finite (got {value})")
    for name in ("fx", "fy"):
        if getattr(message, name) <= 0:
            raise invalid(f"{field}.{name}", f"must be positive (got {getattr(message, name)})")
    if message.width == 0 or message.height == 0:
        raise invalid(field, f"width and height must be positive (got {message.width}x{message.height})")
    if message.width * message.height > max_pixels:
        raise exhausted(
            field, f"{message.width}x{message.height} exceeds the server limit of {max_pixels} pixels"
        )
    return Intrinsics(message.fx, message.fy, message.cx, message.cy, message.width, message.height)


def color_image(message: pb.ColorImage, camera: Intrinsics, field: str) -> np.ndarray:
    if message.encoding not in COLOR_ENCODINGS:
        raise invalid(f"{field}.encoding", f"must be one of {_names(COLOR_ENCODINGS, color_name)} "
                                           f"(got {color_name(message.encoding)})")
    if not message.data:
        raise invalid(f"{field}.data", "is empty")
    try:
        return decode_color(message.data, message.encoding, camera.width, camera.height)
    except ValueError as error:
        raise invalid(field, error) from None


def depth_image(message: pb.DepthImage, camera: Intrinsics, field: str) -> np.ndarray:
    if message.encoding not in DEPTH_ENCODINGS:
        raise invalid(f"{field}.encoding", f"must be one of {_names(DEPTH_ENCODINGS, depth_name)} "
                                           f"(got {depth_name(message.encoding)})")
    if message.encoding == pb.DEPTH_PNG16 and not (math.isfinite(message.depth_scale) and message.depth_scale > 0):
        raise invalid(f"{field}.depth_scale",
                      f"must be positive and finite for DEPTH_PNG16 (got {message.depth_scale})")
    if not message.data:
        raise invalid(f"{field}.data", "is empty")
    try:
        return decode_depth(message.data, message.encoding, message.depth_scale, camera.width, camera.height)
    except ValueError as error:
        raise invalid(field, error) from None


def frame(message: pb.Frame, max_pixels: int) -> Frame:
    """A fully checked and decoded engine Frame; cheap checks run before any decoding."""
    seconds = timestamp(message)
    c2w = pose(message.c2w, "c2w")
    if not message.HasField("color_intrinsics"):
        raise invalid("color_intrinsics", "is required")
    color_camera = intrinsics(message.color_intrinsics, "color_intrinsics", max_pixels)
    depth_camera = (
        intrinsics(message.depth_intrinsics, "depth_intrinsics", max_pixels)
        if message.HasField("depth_intrinsics") else color_camera
    )
    depth_to_color = pose(message.depth_to_color, "depth_to_color") if message.depth_to_color else None
    if not message.HasField("color"):
        raise invalid("color", "is required")
    if not message.HasField("depth"):
        raise invalid("depth", "is required")
    rgb = color_image(message.color, color_camera, "color")
    depth = depth_image(message.depth, depth_camera, "depth")
    return Frame(
        index=int(message.index), rgb=rgb, depth=depth, color_intrinsics=color_camera,
        depth_intrinsics=depth_camera, c2w=c2w, timestamp=seconds,
        depth_to_color=depth_to_color,
    )


@dataclass(frozen=True)
class RenderSpec:
    c2w: np.ndarray
    intrinsics: Intrinsics
    color: bool
    depth: bool
    color_encoding: int
    depth_encoding: int
    jpeg_quality: int


def render_request(message: pb.RenderRequest, max_pixels: int) -> RenderSpec:
    c2w = pose(message.c2w, "c2w")
    if not message.HasField("intrinsics"):
        raise invalid("intrinsics", "is required")
    camera = intrinsics(message.intrinsics, "intrinsics", max_pixels)
    outputs = set(message.outputs) or {pb.RENDER_OUTPUT_COLOR, pb.RENDER_OUTPUT_DEPTH}
    if not outputs <= {pb.RENDER_OUTPUT_COLOR, pb.RENDER_OUTPUT_DEPTH}:
        got = ", ".join(pb.RenderOutput.Name(v) if v in pb.RenderOutput.values() else str(v) for v in sorted(outputs))
        raise invalid("outputs", f"may hold only RENDER_OUTPUT_COLOR and RENDER_OUTPUT_DEPTH (got {got})")
    color_encoding = message.color_encoding or pb.COLOR_PNG
    if color_encoding not in COLOR_ENCODINGS:
        raise invalid("color_encoding", f"must be one of {_names(COLOR_ENCODINGS, color_name)} "
                                        f"(got {color_name(color_encoding)})")
    depth_encoding = message.depth_encoding or pb.DEPTH_PNG16
    if depth_encoding not in DEPTH_ENCODINGS:
        raise invalid("depth_encoding", f"must be one of {_names(DEPTH_ENCODINGS, depth_name)} "
                                        f"(got {depth_name(depth_encoding)})")
    if message.jpeg_quality > 100:
        raise invalid("jpeg_quality", f"must be 1..100 or 0 for the default (got {message.jpeg_quality})")
    return RenderSpec(
        c2w=c2w, intrinsics=camera,
        color=pb.RENDER_OUTPUT_COLOR in outputs, depth=pb.RENDER_OUTPUT_DEPTH in outputs,
        color_encoding=color_encoding, depth_encoding=depth_encoding,
        jpeg_quality=message.jpeg_quality or DEFAULT_JPEG_QUALITY,
    )


def _names(encodings: tuple[int, ...], name: Callable[[int], str]) -> str:
    return ", ".join(name(encoding) for encoding in encodings)
