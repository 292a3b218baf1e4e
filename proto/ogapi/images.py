"""Encode and decode the colour and depth images carried by frames and renders.

Decoders raise ValueError with a short reason (the caller prefixes the field name) that names
encodings as the .proto spells them (``COLOR_JPEG``, ``DEPTH_PNG16``). Compressed
images are sniffed before decoding so that a mislabelled or oversized image is refused without
spending memory on it.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

import cv2
import numpy as np

from ogapi.v1 import mapping_pb2 as pb

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
JPEG_SIGNATURE = b"\xff\xd8"
PNG_GRAY = 0
# JPEG start-of-frame markers carry the image size; C4, C8 and CC share the range but do not.
JPEG_SOF_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
JPEG_STANDALONE_MARKERS = frozenset({0x01, *range(0xD0, 0xD9)})
MAX_DEPTH_UNITS = 65535
DEFAULT_JPEG_QUALITY = 90
COLOR_ENCODINGS = (pb.COLOR_JPEG, pb.COLOR_PNG, pb.COLOR_RAW_RGB8, pb.COLOR_RAW_F32)
DEPTH_ENCODINGS = (pb.DEPTH_PNG16, pb.DEPTH_RAW_F32)
COMPRESSED_FORMATS = {pb.COLOR_JPEG: "jpeg", pb.COLOR_PNG: "png"}  # as ``sniff`` names them
# The largest side each compressed format can be written with: libjpeg's JPEG_MAX_DIMENSION
# (the format's own field holds 65535) and libpng's default user limit (OpenCV keeps it).
MAX_ENCODED_SIDE = {"jpeg": 65500, "png": 1_000_000}


def color_name(encoding: int) -> str:
    """The .proto's name of a colour encoding number (the number itself when it has none)."""
    return pb.ColorEncoding.Name(encoding) if encoding in pb.ColorEncoding.values() else str(encoding)


def depth_name(encoding: int) -> str:
    """The .proto's name of a depth encoding number (the number itself when it has none)."""
    return pb.DepthEncoding.Name(encoding) if encoding in pb.DepthEncoding.values() else str(encoding)


@dataclass(frozen=True)
class ImageHeader:
    format: str  # "png" or "jpeg"
    width: int
    height: int
    bit_depth: int = 8
    gray: bool = False


def _png_header(data: bytes) -> ImageHeader:
    if len(data) < 29 or data[12:16] != b"IHDR":
        raise ValueError("PNG data is truncated before its IHDR header")
    width, height, bit_depth, colour_type = struct.unpack(">IIBB", data[16:26])
    return ImageHeader("png", width, height, bit_depth, colour_type == PNG_GRAY)


def _jpeg_header(data: bytes) -> ImageHeader:
    position = 2
    while position + 4 <= len(data):
        if data[position] != 0xFF:
            raise ValueError(f"JPEG data is corrupt (no marker at byte {position})")
        marker = data[position + 1]
        if marker == 0xFF:  # fill byte
            position += 1
            continue
        if marker in JPEG_STANDALONE_MARKERS:
            position += 2
            continue
        (length,) = struct.unpack(">H", data[position + 2 : position + 4])
        if marker in JPEG_SOF_MARKERS:
            if position + 9 > len(data):
                break
            height, width = struct.unpack(">HH", data[position + 5 : position + 9])
            return ImageHeader("jpeg", width, height, 8, data[position + 9 : position + 10] == b"\x01")
        position += 2 + length
    raise ValueError("JPEG data has no frame header (truncated or not a JPEG)")


def sniff(data: bytes) -> ImageHeader:
    """Format and size of PNG or JPEG bytes, read from the header only."""
    if data.startswith(PNG_SIGNATURE):
        return _png_header(data)
    if data.startswith(JPEG_SIGNATURE):
        return _jpeg_header(data)
    raise ValueError("data is neither PNG nor JPEG")


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    """[0, 1] float colour to 8 bits, rounding (lossless for images that came from 8 bits)."""
    if rgb.dtype == np.uint8:
        return rgb
    return np.clip(np.rint(np.asarray(rgb, dtype=np.float32) * 255.0), 0, 255).astype(np.uint8)


def encode_color(rgb: np.ndarray, encoding: int, jpeg_quality: int = DEFAULT_JPEG_QUALITY) -> bytes:
    """Colour (H, W, 3), float in [0, 1] or uint8, as the bytes of ``encoding``."""
    if encoding == pb.COLOR_RAW_F32:
        return np.ascontiguousarray(rgb, dtype="<f4").tobytes()
    pixels = to_uint8(rgb)
    if encoding == pb.COLOR_RAW_RGB8:
        return np.ascontiguousarray(pixels).tobytes()
    check_encodable(rgb.shape[1], rgb.shape[0], encoded_format(encoding))
    bgr = cv2.cvtColor(pixels, cv2.COLOR_RGB2BGR)
    if encoding == pb.COLOR_PNG:
        ok, buffer = cv2.imencode(".png", bgr)
    elif encoding == pb.COLOR_JPEG:
        ok, buffer = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    else:
        raise ValueError(f"unknown colour encoding {color_name(encoding)}")
    if not ok:
        raise ValueError("colour encoding failed")
    return buffer.tobytes()


def decode_color(data: bytes, encoding: int, width: int, height: int) -> np.ndarray:
    """Colour bytes of a known size to float32 (H, W, 3) in [0, 1]."""
    if encoding == pb.COLOR_RAW_RGB8:
        _check_length(data, height * width * 3, encoding)
        return np.frombuffer(data, np.uint8).reshape(height, width, 3).astype(np.float32) / 255.0
    if encoding == pb.COLOR_RAW_F32:
        _check_length(data, height * width * 3 * 4, encoding)
        rgb = np.frombuffer(data, "<f4").reshape(height, width, 3).astype(np.float32)
        if not np.all(np.isfinite(rgb)):
            raise ValueError("COLOR_RAW_F32 data holds non-finite values")
        return np.clip(rgb, 0.0, 1.0)
    expected = COMPRESSED_FORMATS.get(encoding)
    if expected is None:
        raise ValueError(f"unknown colour encoding {color_name(encoding)}")
    header = sniff(data)
    if header.format != expected:
        raise ValueError(f"data is {header.format.upper()} but the encoding says {color_name(encoding)}")
    _check_size(header, width, height)
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if bgr is None:
        raise ValueError(f"{color_name(encoding)} data could not be decoded")
    _check_size(ImageHeader(expected, bgr.shape[1], bgr.shape[0]), width, height)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB).astype(np.float32) / 255.0


def encode_depth(depth: np.ndarray, encoding: int, depth_scale: float = 1000.0) -> bytes:
    """Depth in metres as bytes; PNG16 stores round(metres * scale) with 0 where out of range."""
    depth = np.asarray(depth, dtype=np.float32)
    if encoding == pb.DEPTH_RAW_F32:
        return np.ascontiguousarray(depth, dtype="<f4").tobytes()
    if encoding != pb.DEPTH_PNG16:
        raise ValueError(f"unknown depth encoding {depth_name(encoding)}")
    check_encodable(depth.shape[1], depth.shape[0], encoded_format(encoding, depth=True))
    units = np.where(np.isfinite(depth), depth, 0.0) * depth_scale
    units = np.where((units > 0) & (units <= MAX_DEPTH_UNITS), np.rint(units), 0).astype(np.uint16)
    ok, buffer = cv2.imencode(".png", units)
    if not ok:
        raise ValueError("depth encoding failed")
    return buffer.tobytes()


def decode_depth(data: bytes, encoding: int, depth_scale: float, width: int, height: int) -> np.ndarray:
    """Depth bytes of a known size to float32 metres, 0 where invalid."""
    if encoding == pb.DEPTH_RAW_F32:
        _check_length(data, height * width * 4, encoding, depth=True)
        depth = np.frombuffer(data, "<f4").reshape(height, width).astype(np.float32)
        depth[~np.isfinite(depth)] = 0.0
        if np.any(depth < 0):
            raise ValueError("DEPTH_RAW_F32 data holds negative values")
        return depth
    if encoding != pb.DEPTH_PNG16:
        raise ValueError(f"unknown depth encoding {depth_name(encoding)}")
    if not usable_depth_scale(depth_scale):
        raise ValueError(f"depth_scale must be positive and finite for DEPTH_PNG16 (got {depth_scale})")
    header = sniff(data)
    if header.format != "png" or header.bit_depth != 16 or not header.gray:
        raise ValueError("DEPTH_PNG16 data must be a single-channel 16-bit PNG")
    _check_size(header, width, height)
    units = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if units is None or units.dtype != np.uint16 or units.ndim != 2:
        raise ValueError("DEPTH_PNG16 data could not be decoded")
    return units.astype(np.float32) / np.float32(depth_scale)


def check_encodable(width: int, height: int, image_format: str) -> None:
    """Raise ValueError when an image of this size cannot be written as ``image_format`` ("jpeg" or
    "png"; other names, the raw encodings, have no limit of their own)."""
    limit = MAX_ENCODED_SIDE.get(image_format)
    if limit is not None and max(width, height) > limit:
        raise ValueError(f"{image_format.upper()} images are at most {limit} pixels a side (got {width}x{height})")


def encoded_format(encoding: int, depth: bool = False) -> str:
    """The compressed format ("jpeg", "png") a colour or depth encoding writes, or "" for a raw one."""
    if depth:
        return "png" if encoding == pb.DEPTH_PNG16 else ""
    return COMPRESSED_FORMATS.get(encoding, "")


def usable_depth_scale(depth_scale: float) -> bool:
    """Positive, finite and a normal float32 (depth is divided by it in float32: 1e-300 would make it infinite)."""
    float32 = np.finfo(np.float32)
    return bool(float32.tiny <= depth_scale <= float32.max)


def _check_length(data: bytes, expected: int, encoding: int, depth: bool = False) -> None:
    if len(data) != expected:
        name = depth_name(encoding) if depth else color_name(encoding)
        raise ValueError(f"{name} data has {len(data)} bytes, the image size needs {expected}")


def _check_size(header: ImageHeader, width: int, height: int) -> None:
    if (header.width, header.height) != (width, height):
        raise ValueError(
            f"image is {header.width}x{header.height} but its intrinsics say {width}x{height}"
        )
