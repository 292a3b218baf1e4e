"""``sensor_msgs/Image`` and ``sensor_msgs/CompressedImage`` to colour in [0, 1] and depth in metres.

Raw colour: rgb8, bgr8, rgba8, bgra8, mono8. Raw depth: 16UC1 in millimetres (0 invalid), 32FC1 in
metres (NaN or 0 invalid), either byte order, rows padded to ``step`` allowed. Compressed colour is
any JPEG or PNG OpenCV reads (image_transport's "compressed": BGR order inside, as OpenCV wants).
Compressed depth is image_transport's "compressedDepth": a 12-byte ``ConfigHeader`` (int32 format,
float32 depthQuantA, depthQuantB) then a PNG, holding millimetres for 16UC1 and, for 32FC1, the
quantised inverse depth ``q = A / z + B`` (0 invalid), so ``z = A / (q - B)``; or the "compressed"
plugin's plain 16-bit PNG of 16UC1 millimetres (format "16UC1; png compressed"). A compressed image's
size is read from its PNG or JPEG header and checked before it is decoded: a PNG of 20000x20000
zeros is 1.2 MB and would decode to gigabytes.
"""

from __future__ import annotations

import struct
from collections.abc import Callable

import cv2
import numpy as np

from ogmapping.datasets.base import decode_depth, opencv_to_rgb

COLOR_ENCODINGS = ("rgb8", "bgr8", "rgba8", "bgra8", "mono8")
DEPTH_ENCODINGS = ("16UC1", "32FC1")
MILLIMETRES_PER_METRE = 1000.0
COMPRESSED_DEPTH_HEADER = struct.Struct("<iff")
_CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1, "16UC1": 1, "32FC1": 1}
_DTYPES = {"16UC1": "u2", "32FC1": "f4"}
# The most pixels an image may have: 8K video and 50-megapixel machine-vision cameras fit; its
# colour in float32 is 600 MB.
MAX_IMAGE_PIXELS = 8192 * 6144
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
JPEG_SIGNATURE = b"\xff\xd8"
# JPEG start-of-frame markers carry the image size; C4, C8 and CC share the range but do not.
JPEG_SIZE_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
JPEG_LONE_MARKERS = frozenset({0x01, *range(0xD0, 0xD9)})  # markers without a length after them
SizeCheck = Callable[[int, int], None]  # (width, height) -> None, or ValueError for a size refused


def check_pixels(width: int, height: int) -> None:
    """ValueError for an image larger than ``MAX_IMAGE_PIXELS``."""
    if width * height > MAX_IMAGE_PIXELS:
        raise ValueError(f"an image of {width}x{height} is over the reader's limit of {MAX_IMAGE_PIXELS} pixels")


def is_compressed_depth(format: str) -> bool:
    """image_transport marks compressedDepth payloads in CompressedImage.format."""
    return "compresseddepth" in format.lower().replace(" ", "")


def _pixels(message: object, dtype: np.dtype) -> np.ndarray:
    """The (H, W, C) array of a raw Image, row padding cut off."""
    height, width, step = int(message.height), int(message.width), int(message.step)  # type: ignore[attr-defined]
    encoding = str(message.encoding)  # type: ignore[attr-defined]
    channels = _CHANNELS[encoding]
    row_bytes = width * channels * dtype.itemsize
    data = np.asarray(message.data, dtype=np.uint8)  # type: ignore[attr-defined]
    if step < row_bytes or data.size < step * height:
        raise ValueError(f"{encoding} image of {width}x{height} needs {row_bytes} bytes a row and {height} rows; "
                         f"it has step {step} and {data.size} bytes")
    rows = data[: step * height].reshape(height, step)[:, :row_bytes]
    return np.ascontiguousarray(rows).view(dtype).reshape(height, width, channels)


def image_color(message: object) -> np.ndarray:
    """A raw colour Image as float32 (H, W, 3) RGB in [0, 1]."""
    encoding = str(message.encoding)  # type: ignore[attr-defined]
    if encoding not in COLOR_ENCODINGS:
        raise ValueError(f"colour image encoding {encoding!r} is not supported; expected one of "
                         f"{', '.join(COLOR_ENCODINGS)}")
    pixels = _pixels(message, np.dtype(np.uint8))
    if encoding in ("rgb8", "rgba8"):
        return pixels[:, :, :3].astype(np.float32) * np.float32(1.0 / 255.0)
    return opencv_to_rgb(pixels[:, :, 0] if encoding == "mono8" else pixels)


def image_depth(message: object) -> np.ndarray:
    """A raw depth Image as float32 (H, W) metres, invalid pixels 0."""
    encoding = str(message.encoding)  # type: ignore[attr-defined]
    if encoding not in DEPTH_ENCODINGS:
        raise ValueError(f"depth image encoding {encoding!r} is not supported; expected 16UC1 (mm) or 32FC1 (m)")
    order = ">" if message.is_bigendian else "<"  # type: ignore[attr-defined]
    raw = _pixels(message, np.dtype(order + _DTYPES[encoding]))[:, :, 0]
    raw = raw.astype(raw.dtype.newbyteorder("="))
    return decode_depth(raw, MILLIMETRES_PER_METRE if encoding == "16UC1" else 1.0)


def _jpeg_size(data: bytes) -> tuple[int, int] | None:
    position = len(JPEG_SIGNATURE)
    while position + 4 <= len(data) and data[position] == 0xFF:
        marker = data[position + 1]
        if marker == 0xFF or marker in JPEG_LONE_MARKERS:  # a fill byte, or a marker without a segment
            position += 1 if marker == 0xFF else 2
            continue
        if marker in JPEG_SIZE_MARKERS and position + 9 <= len(data):
            height, width = struct.unpack_from(">HH", data, position + 5)
            return width, height
        position += 2 + struct.unpack_from(">H", data, position + 2)[0]
    return None


def encoded_size(data: np.ndarray, what: str) -> tuple[int, int]:
    """(width, height) from a PNG's or a JPEG's header, without decoding it."""
    head = np.asarray(data, dtype=np.uint8).tobytes()
    size = None
    if head.startswith(PNG_SIGNATURE):
        size = struct.unpack_from(">II", head, 16) if len(head) >= 24 and head[12:16] == b"IHDR" else None
    elif head.startswith(JPEG_SIGNATURE):
        size = _jpeg_size(head)
    else:
        raise ValueError(f"the {what} is neither a JPEG nor a PNG")
    if size is None:
        raise ValueError(f"the {what} has no readable size in its header (cut or corrupt)")
    return size


def _decode_png_or_jpeg(data: np.ndarray, what: str, check: SizeCheck) -> np.ndarray:
    check(*encoded_size(data, what))
    image = cv2.imdecode(np.asarray(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"cannot decode the {what} (not a JPEG or PNG OpenCV reads)")
    return image


def _sixteen_bit(raw: np.ndarray) -> np.ndarray:
    if raw.ndim != 2 or raw.dtype != np.uint16:
        raise ValueError(f"a depth PNG must be one 16-bit channel, got {raw.dtype} with shape {raw.shape}")
    return raw


def compressed_color(message: object, check: SizeCheck = check_pixels) -> np.ndarray:
    """A compressed colour image (JPEG or PNG) as float32 (H, W, 3) RGB in [0, 1]; ``check`` is given
    the size its header declares before it is decoded."""
    format = str(message.format)  # type: ignore[attr-defined]
    if is_compressed_depth(format):
        raise ValueError(f"a compressedDepth image ({format!r}) is not colour")
    return opencv_to_rgb(_decode_png_or_jpeg(message.data, f"compressed colour image ({format!r})", check))  # type: ignore[attr-defined]


def is_plain_png_depth(format: str) -> bool:
    """image_transport's "compressed" plugin given 16UC1 depth writes a plain 16-bit PNG ("16UC1; png ...")."""
    return not is_compressed_depth(format) and format.split(";")[0].strip() == "16UC1"


def compressed_depth(message: object, check: SizeCheck = check_pixels) -> np.ndarray:
    """A compressedDepth image, or a plain 16UC1 PNG, as float32 (H, W) metres, invalid pixels 0;
    ``check`` is given the size its PNG header declares before it is decoded."""
    format = str(message.format)  # type: ignore[attr-defined]
    data = np.asarray(message.data, dtype=np.uint8)  # type: ignore[attr-defined]
    if is_plain_png_depth(format):
        return decode_depth(_sixteen_bit(_decode_png_or_jpeg(data, f"16UC1 PNG ({format!r})", check)),
                            MILLIMETRES_PER_METRE)
    if not is_compressed_depth(format):
        raise ValueError(f"compressed depth must be image_transport's compressedDepth or a 16UC1 PNG; "
                         f"format is {format!r}")
    encoding = format.split(";")[0].strip()
    if "rvl" in format.lower():
        raise ValueError(f"compressedDepth with RVL ({format!r}) is not supported; record with PNG")
    if encoding not in DEPTH_ENCODINGS:
        raise ValueError(f"compressedDepth of encoding {encoding!r} is not supported; expected 16UC1 or 32FC1")
    if data.size <= COMPRESSED_DEPTH_HEADER.size:
        raise ValueError(f"compressedDepth image of {data.size} bytes holds no PNG after its 12-byte header")
    _, quant_a, quant_b = COMPRESSED_DEPTH_HEADER.unpack(data[: COMPRESSED_DEPTH_HEADER.size].tobytes())
    png = data[COMPRESSED_DEPTH_HEADER.size :]
    raw = _sixteen_bit(_decode_png_or_jpeg(png, f"compressedDepth PNG ({format!r})", check))
    if encoding == "16UC1":
        return decode_depth(raw, MILLIMETRES_PER_METRE)
    depth = np.zeros(raw.shape, dtype=np.float32)
    valid = raw > 0
    depth[valid] = np.float32(quant_a) / (raw[valid].astype(np.float32) - np.float32(quant_b))
    return decode_depth(depth, 1.0)
