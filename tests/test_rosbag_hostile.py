"""Hostile bags: compressed images whose headers claim far more pixels than their CameraInfo (a PNG of
20000x20000 zeros is 1.2 MB) are refused before they are decoded, CameraInfo beyond a sane size at
once, and the command lines say so in one line."""

from __future__ import annotations

import re
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

pytest.importorskip("rosbags")

from rosbag_writer import BagRecorder, compressed_depth_16, encode_png
from test_rosbag_reader import N, depth_mm, published_k, rgb8, stamp

from ogmapping.cli import commands
from ogmapping.datasets import open_dataset
from ogmapping.datasets.rosbag import images
from ogmapping.datasets.rosbag.topics import BagTopicError
from ogmapping.datasets.synthetic import SyntheticSource

HUGE = 20000
FRAME = "cam_optical_frame"


def png_header_only(width: int, height: int, bit_depth: int = 8, colour_type: int = 2) -> bytes:
    """A PNG's signature, IHDR and IEND: its header says ``width`` x ``height``, it holds no pixels."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", width, height, bit_depth, colour_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IEND", b"")


def jpeg_claiming(width: int, height: int) -> bytes:
    """A real 48x36 JPEG whose frame header is changed to say ``width`` x ``height``."""
    data = bytearray(cv2.imencode(".jpg", np.zeros((36, 48, 3), np.uint8))[1].tobytes())
    sof = data.index(b"\xff\xc0")
    data[sof + 5 : sof + 9] = struct.pack(">HH", height, width)
    return bytes(data)


@pytest.fixture(scope="module")
def frames():
    return [SyntheticSource(n_frames=N, width=48, height=36)[i] for i in range(N)]


def write_bag(path: Path, frames, colour: bytes | None = None, depth: bytes | None = None,
              info_size: tuple[int, int] = (48, 36)) -> Path:
    """Compressed colour and compressedDepth frames with a pose each; ``colour`` or ``depth`` stand in for
    every frame's payload when given."""
    with BagRecorder(path, ros2=True) as bag:
        for i in range(2):
            t, frame = stamp(i), frames[i]
            bag.write("/cam/color/image_raw/compressed", t, bag.compressed(
                t, FRAME, colour or encode_png(rgb8(frame)[:, :, ::-1]), "rgb8; png compressed bgr8"))
            bag.write("/cam/color/camera_info", t, bag.camera_info(t, FRAME, *info_size, published_k(frame)))
            bag.write("/cam/depth/image_raw/compressedDepth", t, bag.compressed(
                t, FRAME, depth or compressed_depth_16(depth_mm(frame)), "16UC1; compressedDepth png"))
            bag.write("/pose", t, bag.pose_stamped(t, "map", frame.c2w))
    return path


@pytest.fixture
def decoded(monkeypatch: pytest.MonkeyPatch) -> list[bytes]:
    """The bytes of every image OpenCV is asked to decode."""
    seen: list[bytes] = []
    original = cv2.imdecode

    def decode(data: np.ndarray, flags: int) -> np.ndarray | None:
        seen.append(np.asarray(data).tobytes())
        return original(data, flags)

    monkeypatch.setattr(cv2, "imdecode", decode)
    return seen


@pytest.mark.parametrize("payload", ["png", "jpeg"])
def test_a_colour_image_larger_than_its_camera_info_is_never_decoded(tmp_path: Path, frames, payload: str,
                                                                     decoded: list[bytes]) -> None:
    colour = png_header_only(HUGE, HUGE) if payload == "png" else jpeg_claiming(HUGE, HUGE - 1)
    source = open_dataset(str(write_bag(tmp_path / "bomb.mcap", frames, colour=colour)))
    size = f"{HUGE}x{HUGE}" if payload == "png" else f"{HUGE}x{HUGE - 1}"
    with pytest.raises(ValueError, match=rf"/cam/color/image_raw/compressed at \d+ ns: image is {size} but its "
                                         r"CameraInfo says 48x36"):
        source[0]
    assert colour not in decoded


def test_a_depth_image_larger_than_its_camera_info_is_never_decoded(tmp_path: Path, frames,
                                                                    decoded: list[bytes]) -> None:
    depth = struct.pack("<iff", 0, 0.0, 0.0) + png_header_only(HUGE, HUGE, bit_depth=16, colour_type=0)
    source = open_dataset(str(write_bag(tmp_path / "bomb.mcap", frames, depth=depth)))
    with pytest.raises(ValueError, match=rf"image is {HUGE}x{HUGE} but its CameraInfo \(the colour camera's"):
        source[0]
    assert len(decoded) == 1 and depth[12:] not in decoded  # the colour image only


def test_camera_info_beyond_the_limit_is_refused_at_once(tmp_path: Path, frames) -> None:
    path = write_bag(tmp_path / "huge.mcap", frames, colour=png_header_only(HUGE, HUGE), info_size=(HUGE, HUGE))
    with pytest.raises(ValueError, match=rf"/cam/color/camera_info: an image of {HUGE}x{HUGE} is over the reader's "
                                         rf"limit of {images.MAX_IMAGE_PIXELS} pixels"):
        open_dataset(str(path))


def test_a_compressed_image_neither_png_nor_jpeg_is_refused(tmp_path: Path, frames) -> None:
    bmp = cv2.imencode(".bmp", np.zeros((36, 48, 3), np.uint8))[1].tobytes()
    source = open_dataset(str(write_bag(tmp_path / "bmp.mcap", frames, colour=bmp)))
    with pytest.raises(ValueError, match=r"compressed colour image \('rgb8; png compressed bgr8'\) is neither a JPEG "
                                         "nor a PNG"):
        source[0]


@pytest.mark.parametrize("size", [(48, 36), (7, 5), (640, 1)])
def test_sizes_read_from_headers_are_the_decoded_sizes(size: tuple[int, int]) -> None:
    width, height = size
    pixels = np.random.default_rng(0).integers(0, 255, (height, width, 3), dtype=np.uint8)
    encoded = [encode_png(pixels), encode_png(pixels[:, :, 0].astype(np.uint16) * 200)]
    encoded += [cv2.imencode(".jpg", pixels, flags)[1].tobytes()
                for flags in ([], [cv2.IMWRITE_JPEG_PROGRESSIVE, 1], [cv2.IMWRITE_JPEG_OPTIMIZE, 1])]
    for data in encoded:
        array = np.frombuffer(data, np.uint8)
        decoded = cv2.imdecode(array, cv2.IMREAD_UNCHANGED)
        assert images.encoded_size(array, "image") == (decoded.shape[1], decoded.shape[0]) == size


def test_ogmap_run_refuses_the_bomb_in_one_line(tmp_path: Path, frames, capsys: pytest.CaptureFixture) -> None:
    path = write_bag(tmp_path / "bomb.mcap", frames, colour=png_header_only(HUGE, HUGE))
    code = commands.main(["run", "--bag", str(path), "--pose-topic", "/pose", "--frames", "0:2", "--device", "cpu",
                          "--out", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("ogmap: error: ") and f"image is {HUGE}x{HUGE}" in err


def test_an_unsupported_encoding_is_named(tmp_path: Path, frames) -> None:
    path = tmp_path / "yuv.mcap"
    with BagRecorder(path, ros2=True) as bag:
        for i in range(2):
            t, frame = stamp(i), frames[i]
            yuv = cv2.cvtColor(rgb8(frame), cv2.COLOR_RGB2YUV)[:, :, :2].copy()
            bag.write("/camera/color/image_raw", t, bag.image(t, FRAME, yuv, "yuv422"))
            bag.write("/camera/color/camera_info", t, bag.camera_info(t, FRAME, 48, 36, published_k(frame)))
            bag.write("/camera/depth/image_raw", t, bag.image(t, FRAME, depth_mm(frame), "16UC1"))
    why = ("(/camera/color/image_raw has encoding yuv422, which is not supported; colour is one of rgb8, bgr8, "
           "rgba8, bgra8, mono8, depth 16UC1 or 32FC1)")
    with pytest.raises(BagTopicError, match=re.escape(f"no colour image topic {why}")):
        open_dataset(str(path))
    with pytest.raises(BagTopicError, match=re.escape(
            f"--color-topic /camera/color/image_raw (sensor_msgs/msg/Image) does not hold colour image {why}")):
        open_dataset(str(path), "bag", color_topic="/camera/color/image_raw")


def write_not_a_bag(path: Path, kind: str) -> Path:
    noise = np.random.default_rng(7).integers(0, 256, 4096, dtype=np.uint8).tobytes()
    target = path / f"noise.{kind}"
    if kind == "folder":
        target.mkdir()
        (target / "metadata.yaml").write_bytes(noise)
    else:
        target.write_bytes(noise if kind != "empty.mcap" else b"")
    return target


@pytest.mark.parametrize("kind", ["bag", "mcap", "db3", "folder", "empty.mcap"])
def test_random_bytes_are_not_a_bag(tmp_path: Path, kind: str, capsys: pytest.CaptureFixture) -> None:
    path = write_not_a_bag(tmp_path, kind)
    with pytest.raises(ValueError, match=rf"^not a ROS bag: {re.escape(str(path))}"):
        open_dataset(str(path), "bag")
    assert commands.main(["run", "--bag", str(path), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("ogmap: error: not a ROS bag: ") and "codec" not in err


def test_a_file_with_only_the_mcap_magic_is_a_damaged_bag(tmp_path: Path) -> None:
    path = tmp_path / "magic.mcap"
    path.write_bytes(b"\x89MCAP0\r\n")
    with pytest.raises(ValueError, match=rf"^cannot open {re.escape(str(path))} as a ROS bag: "):
        open_dataset(str(path))
