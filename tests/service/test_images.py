"""Encoding helpers: every encoding round-trips, and broken or mislabelled data is refused."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from ogapi.images import decode_color, decode_depth, encode_color, encode_depth, sniff
from ogapi.v1 import mapping_pb2 as pb

RNG = np.random.default_rng(0)
RGB8 = RNG.integers(0, 256, (30, 40, 3), dtype=np.uint8)
RGB = RGB8.astype(np.float32) / 255.0
DEPTH = np.round(RNG.uniform(0.5, 4.0, (30, 40)), 3).astype(np.float32)
DEPTH[0, :5] = 0.0


@pytest.mark.parametrize("encoding", [pb.COLOR_PNG, pb.COLOR_RAW_RGB8, pb.COLOR_RAW_F32])
def test_lossless_color_round_trips(encoding: int) -> None:
    decoded = decode_color(encode_color(RGB, encoding), encoding, 40, 30)
    assert decoded.dtype == np.float32 and decoded.shape == (30, 40, 3)
    np.testing.assert_allclose(decoded, RGB, atol=1e-6)


def test_jpeg_round_trip_is_close() -> None:
    smooth = cv2.GaussianBlur(RGB, (9, 9), 3)
    decoded = decode_color(encode_color(smooth, pb.COLOR_JPEG, 95), pb.COLOR_JPEG, 40, 30)
    assert np.abs(decoded - smooth).mean() < 0.02


@pytest.mark.parametrize("encoding", [pb.DEPTH_PNG16, pb.DEPTH_RAW_F32])
def test_depth_round_trips(encoding: int) -> None:
    decoded = decode_depth(encode_depth(DEPTH, encoding, 1000.0), encoding, 1000.0, 40, 30)
    np.testing.assert_allclose(decoded, DEPTH, atol=5e-4)


def test_png16_marks_out_of_range_depth_invalid() -> None:
    depth = np.array([[np.nan, -1.0, 70.0, 1.2346]], dtype=np.float32)
    decoded = decode_depth(encode_depth(depth, pb.DEPTH_PNG16, 1000.0), pb.DEPTH_PNG16, 1000.0, 4, 1)
    np.testing.assert_allclose(decoded, [[0.0, 0.0, 0.0, 1.235]], atol=1e-6)


def test_tum_scale_is_respected() -> None:
    units = np.full((2, 3), 5000, np.uint16)
    data = cv2.imencode(".png", units)[1].tobytes()
    np.testing.assert_allclose(decode_depth(data, pb.DEPTH_PNG16, 5000.0, 3, 2), 1.0)


def test_sniff_reads_sizes_without_decoding() -> None:
    png = sniff(encode_color(RGB, pb.COLOR_PNG))
    jpeg = sniff(encode_color(RGB, pb.COLOR_JPEG))
    depth = sniff(encode_depth(DEPTH, pb.DEPTH_PNG16))
    assert (png.format, png.width, png.height, png.bit_depth, png.gray) == ("png", 40, 30, 8, False)
    assert (jpeg.format, jpeg.width, jpeg.height) == ("jpeg", 40, 30)
    assert (depth.bit_depth, depth.gray) == (16, True)


@pytest.mark.parametrize(
    ("data", "encoding", "reason"),
    [
        (b"hello", pb.COLOR_JPEG, "neither PNG nor JPEG"),
        (b"\xff\xd8\xff\xe0\x00\x10JFIF" + b"\x00" * 20, pb.COLOR_JPEG, "JPEG"),
        (encode_color(RGB, pb.COLOR_PNG), pb.COLOR_JPEG, "encoding says COLOR_JPEG"),
        (encode_color(RGB, pb.COLOR_PNG)[:40], pb.COLOR_PNG, "could not be decoded"),
        (encode_color(RGB[:10], pb.COLOR_PNG), pb.COLOR_PNG, "intrinsics say 40x30"),
        (b"\x00" * 11, pb.COLOR_RAW_RGB8, "needs 3600"),
        (np.full((30, 40, 3), np.nan, "<f4").tobytes(), pb.COLOR_RAW_F32, "non-finite"),
        (b"x", 42, "unknown colour encoding"),
    ],
)
def test_bad_color_is_refused(data: bytes, encoding: int, reason: str) -> None:
    with pytest.raises(ValueError, match=reason):
        decode_color(data, encoding, 40, 30)


@pytest.mark.parametrize(
    ("data", "scale", "encoding", "reason"),
    [
        (encode_depth(DEPTH, pb.DEPTH_PNG16), 0.0, pb.DEPTH_PNG16, "depth_scale"),
        (encode_depth(DEPTH, pb.DEPTH_PNG16), float("nan"), pb.DEPTH_PNG16, "depth_scale"),
        (encode_color(RGB, pb.COLOR_PNG), 1000.0, pb.DEPTH_PNG16, "single-channel 16-bit"),
        (encode_color(RGB, pb.COLOR_JPEG), 1000.0, pb.DEPTH_PNG16, "single-channel 16-bit"),
        (np.full((30, 40), -1.0, "<f4").tobytes(), 0.0, pb.DEPTH_RAW_F32, "negative"),
        (b"\x00" * 8, 0.0, pb.DEPTH_RAW_F32, "needs 4800"),
    ],
)
def test_bad_depth_is_refused(data: bytes, scale: float, encoding: int, reason: str) -> None:
    with pytest.raises(ValueError, match=reason):
        decode_depth(data, encoding, scale, 40, 30)


def test_raw_depth_non_finite_means_invalid() -> None:
    depth = np.array([[np.nan, np.inf, 2.0]], "<f4")
    np.testing.assert_array_equal(decode_depth(depth.tobytes(), pb.DEPTH_RAW_F32, 0.0, 3, 1), [[0.0, 0.0, 2.0]])
