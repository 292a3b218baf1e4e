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
    check_encodable,
    color_name,
    decode_color,
    decode_depth,
    depth_name,
    encoded_format,
    usable_depth_scale,
)
from ogapi.v1 import mapping_pb2 as pb

from ogmapping.config import OctreeConfig
from ogmapping.frames.camera import Intrinsics, validate_pose
from ogmapping.frames.frame import Frame
from ogmapping.frames.preprocess import MAX_FOOTPRINT
from ogmapping.structure import extent
from ogserver.errors import exhausted, invalid

SESSION_ID_PATTERN = re.compile(r"[0-9a-f]{32}")
RECORDABLE_NANOSECONDS = 2**64  # exclusive
MAX_TIMESTAMP_SECONDS = RECORDABLE_NANOSECONDS / 1e9
# A pinhole camera the engine computes with in float32: a field of view between about 0.06 and 179
# degrees, and a principal point within ten image sizes of the image (fx = 1e300 is no camera).
FOCAL_RANGE = (1e-2, 1e3)  # fx and fy, as multiples of the image's larger side
MAX_PRINCIPAL_OFFSET = 10.0  # |cx - width / 2| and |cy - height / 2|, as multiples of the larger side


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
        raise exhausted(field, f"{message.width}x{message.height} exceeds the server limit of {max_pixels} pixels "
                               f"(limits.max_image_pixels)")
    side = max(message.width, message.height)
    low, high = FOCAL_RANGE[0] * side, FOCAL_RANGE[1] * side
    for name in ("fx", "fy"):
        if not low <= getattr(message, name) <= high:
            raise invalid(f"{field}.{name}", f"must lie in [{low:g}, {high:g}] for a {message.width}x{message.height} "
                                             f"image (got {getattr(message, name):g})")
    for name, centre in (("cx", message.width / 2), ("cy", message.height / 2)):
        if abs(getattr(message, name) - centre) > MAX_PRINCIPAL_OFFSET * side:
            raise invalid(f"{field}.{name}", f"must lie within {MAX_PRINCIPAL_OFFSET:g} image sizes of the image "
                                             f"centre (got {getattr(message, name):g})")
    return Intrinsics(message.fx, message.fy, message.cx, message.cy, message.width, message.height)


def registration(color_camera: Intrinsics, depth_camera: Intrinsics) -> None:
    """Registration spreads a depth pixel over the colour pixels it covers: refuse the cameras
    where that would be more than ``MAX_FOOTPRINT`` per axis (its work grows as the square)."""
    for name in ("fx", "fy"):
        ratio = getattr(color_camera, name) / getattr(depth_camera, name)
        if ratio > MAX_FOOTPRINT:
            raise invalid(f"depth_intrinsics.{name}", f"the colour camera samples {ratio:g}x as densely as the "
                                                      f"depth camera; registration allows at most {MAX_FOOTPRINT:g}x")


def within_map(c2w: np.ndarray, camera: Intrinsics, octree: OctreeConfig) -> None:
    """Refuse a frame whose points could land beyond what the session's octree can address."""
    reach, radius = extent.frame_radius(c2w, camera, octree.depth_max), extent.map_radius(octree)
    if reach > radius:
        raise invalid("c2w", f"puts the frame's points up to {reach:.0f} m from the origin along an axis; this "
                             f"session's map reaches {radius:.0f} m (set by octree.voxel_size and octree.max_level)")


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
    if message.encoding == pb.DEPTH_PNG16 and not usable_depth_scale(message.depth_scale):
        raise invalid(f"{field}.depth_scale",
                      f"must be positive and finite for DEPTH_PNG16 (got {message.depth_scale})")
    if not message.data:
        raise invalid(f"{field}.data", "is empty")
    try:
        return decode_depth(message.data, message.encoding, message.depth_scale, camera.width, camera.height)
    except ValueError as error:
        raise invalid(field, error) from None


def frame(message: pb.Frame, max_pixels: int, octree: OctreeConfig) -> Frame:
    """A fully checked and decoded engine Frame for a session with ``octree``; cheap checks run
    before any decoding."""
    seconds = timestamp(message)
    c2w = pose(message.c2w, "c2w")
    if not message.HasField("color_intrinsics"):
        raise invalid("color_intrinsics", "is required")
    color_camera = intrinsics(message.color_intrinsics, "color_intrinsics", max_pixels)
    depth_camera = (
        intrinsics(message.depth_intrinsics, "depth_intrinsics", max_pixels)
        if message.HasField("depth_intrinsics") else color_camera
    )
    registration(color_camera, depth_camera)
    within_map(c2w, color_camera, octree)
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
    # The frame whose time c2w is from (RenderRequest.at): by sequence or by timestamp; neither: the map's frame.
    sequence: int | None = None
    timestamp: float | None = None


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
    for wanted, image_format, field in (
        (pb.RENDER_OUTPUT_COLOR in outputs, encoded_format(color_encoding), "color_encoding"),
        (pb.RENDER_OUTPUT_DEPTH in outputs, encoded_format(depth_encoding, depth=True), "depth_encoding"),
    ):
        try:
            if wanted:
                check_encodable(camera.width, camera.height, image_format)
        except ValueError as error:
            raise invalid("intrinsics", f"{error}; ask a smaller render or another {field}") from None
    at = message.WhichOneof("at")
    if at == "sequence" and message.sequence == 0:
        raise invalid("sequence", "must be 1 or more (a frame's FrameAck.sequence)")
    if at == "timestamp" and not math.isfinite(message.timestamp):
        raise invalid("timestamp", f"must be finite (got {message.timestamp})")
    return RenderSpec(
        c2w=c2w, intrinsics=camera,
        sequence=message.sequence if at == "sequence" else None,
        timestamp=message.timestamp if at == "timestamp" else None,
        color=pb.RENDER_OUTPUT_COLOR in outputs, depth=pb.RENDER_OUTPUT_DEPTH in outputs,
        color_encoding=color_encoding, depth_encoding=depth_encoding,
        jpeg_quality=message.jpeg_quality or DEFAULT_JPEG_QUALITY,
    )


def _names(encodings: tuple[int, ...], name: Callable[[int], str]) -> str:
    return ", ".join(name(encoding) for encoding in encodings)


@dataclass(frozen=True)
class CorrectionEntry:
    """One CorrectPoses entry, checked: the frame it names (by sequence or by timestamp) and its rigid pose."""

    field: str  # "poses[3]", for refusals
    sequence: int | None
    timestamp: float | None
    c2w: np.ndarray


def pose_corrections(message: pb.CorrectPosesRequest, max_entries: int) -> list[CorrectionEntry]:
    """The request's entries; RESOURCE_EXHAUSTED beyond ``max_entries``, INVALID_ARGUMENT naming the first entry
    that names no frame or whose pose is not a rigid 4x4."""
    if not message.poses:
        raise invalid("poses", "is empty: no corrections to apply")
    if len(message.poses) > max_entries:
        raise exhausted("poses", f"{len(message.poses)} entries, over the server's limit of {max_entries} a call "
                                 "(limits.max_pose_corrections): send them in batches")
    entries = []
    for position, entry in enumerate(message.poses):
        field = f"poses[{position}]"
        which = entry.WhichOneof("frame")
        if which is None:
            raise invalid(field, "names no frame: set its sequence or its timestamp")
        if which == "sequence" and entry.sequence == 0:
            raise invalid(f"{field}.sequence", "must be 1 or more (the frame's FrameAck.sequence)")
        if which == "timestamp" and not math.isfinite(entry.timestamp):
            raise invalid(f"{field}.timestamp", f"must be finite (got {entry.timestamp})")
        stamp = entry.timestamp if which == "timestamp" else None
        sequence = entry.sequence if which == "sequence" else None
        entries.append(CorrectionEntry(field, sequence, stamp, pose(entry.c2w, f"{field}.c2w")))
    return entries
