"""The bag reader's parts, message by message: headers, every image encoding, CameraInfo and undistortion,
TF interpolation and chains, colour-depth pairing. Messages are built with the distros' own type stores."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

pytest.importorskip("rosbags")

from rosbag_writer import BagRecorder, compressed_depth_16, compressed_depth_32, encode_png

from ogmapping.datasets.rosbag import images
from ogmapping.datasets.rosbag.bagfile import MessageRef
from ogmapping.datasets.rosbag.calibration import Calibration, undistort
from ogmapping.datasets.rosbag.headers import read_header
from ogmapping.datasets.rosbag.pairing import StampedImage, pair_images
from ogmapping.datasets.rosbag.transforms import Track, TransformTree
from ogmapping.frames.rotation import quaternion_pose

STAMP = 1_700_000_123 * 10**9 + 456_789_012
RNG = np.random.default_rng(3)
RGB = RNG.integers(0, 256, (6, 5, 3), dtype=np.uint8)
DEPTH_MM = RNG.integers(300, 5000, (6, 5)).astype(np.uint16)


@pytest.fixture(params=["ros1", "ros2"])
def recorder(request, tmp_path) -> BagRecorder:
    """Builds messages only (nothing is written); ROS 1 and ROS 2 messages differ in field names and bytes."""
    return BagRecorder(tmp_path / "unused", ros2=request.param == "ros2")


def roundtrip(recorder: BagRecorder, message: object) -> object:
    """The message as a reader gets it back from its serialized bytes."""
    name = message.__msgtype__  # type: ignore[attr-defined]
    if recorder.ros2:
        return recorder.store.deserialize_cdr(recorder.store.serialize_cdr(message, name), name)
    return recorder.store.deserialize_ros1(recorder.store.serialize_ros1(message, name), name)


def test_header_read_from_bytes_matches_the_decoded_message(recorder: BagRecorder) -> None:
    message = recorder.image(STAMP, "/cam_optical_frame", RGB, "rgb8")
    name = "sensor_msgs/msg/Image"
    raw = recorder.store.serialize_cdr(message, name) if recorder.ros2 else recorder.store.serialize_ros1(message, name)
    header = read_header(raw, recorder.ros2)
    assert header.stamp_ns == STAMP
    assert header.frame_id == "cam_optical_frame"  # ROS 1's leading slash dropped
    with pytest.raises(ValueError, match="too short for a std_msgs/Header"):
        read_header(bytes(raw)[:6], recorder.ros2)
    with pytest.raises(ValueError, match="too short for its header's frame_id"):
        read_header(bytes(raw)[:20], recorder.ros2)


def test_big_endian_cdr_header() -> None:
    import struct

    raw = b"\x00\x00\x00\x00" + struct.pack(">iII", 12, 34, 4) + b"cam\0"
    assert read_header(raw, ros2=True).stamp_ns == 12 * 10**9 + 34
    assert read_header(raw, ros2=True).frame_id == "cam"
    long_name = "a" * 3000  # longer than any prefix a reader might peek at
    raw = b"\x00\x01\x00\x00" + struct.pack("<iII", 1, 2, len(long_name) + 1) + long_name.encode() + b"\0"
    assert read_header(raw, ros2=True).frame_id == long_name


@pytest.mark.parametrize("encoding", ["rgb8", "bgr8", "rgba8", "bgra8", "mono8"])
def test_raw_colour_encodings(recorder: BagRecorder, encoding: str) -> None:
    pixels = {
        "rgb8": RGB, "bgr8": RGB[:, :, ::-1], "rgba8": np.dstack([RGB, np.full(RGB.shape[:2], 9, np.uint8)]),
        "bgra8": np.dstack([RGB[:, :, ::-1], np.full(RGB.shape[:2], 9, np.uint8)]), "mono8": RGB[:, :, 0],
    }[encoding]
    expected = np.repeat(RGB[:, :, :1], 3, axis=2) if encoding == "mono8" else RGB
    message = roundtrip(recorder, recorder.image(STAMP, "cam", pixels, encoding, pad=3))
    rgb = images.image_color(message)
    assert rgb.dtype == np.float32 and rgb.shape == (6, 5, 3)
    np.testing.assert_allclose(rgb, expected / 255.0, atol=1e-6)


@pytest.mark.parametrize("big_endian", [False, True])
def test_raw_depth_16uc1_is_millimetres(recorder: BagRecorder, big_endian: bool) -> None:
    raw = DEPTH_MM.copy()
    raw[0, 0], raw[1, 1] = 0, 65535  # no measurement
    message = roundtrip(recorder, recorder.image(STAMP, "cam", raw, "16UC1", big_endian=big_endian, pad=2))
    depth = images.image_depth(message)
    expected = raw / 1000.0
    expected[0, 0] = expected[1, 1] = 0.0
    np.testing.assert_allclose(depth, expected, atol=1e-6)


@pytest.mark.parametrize("big_endian", [False, True])
def test_raw_depth_32fc1_is_metres(recorder: BagRecorder, big_endian: bool) -> None:
    metres = (DEPTH_MM / 1000.0).astype(np.float32)
    metres[0, 0], metres[2, 2] = np.nan, -1.0
    message = roundtrip(recorder, recorder.image(STAMP, "cam", metres, "32FC1", big_endian=big_endian))
    depth = images.image_depth(message)
    expected = metres.copy()
    expected[0, 0] = expected[2, 2] = 0.0
    np.testing.assert_array_equal(depth, expected)


def test_unsupported_raw_encodings_are_named(recorder: BagRecorder) -> None:
    message = roundtrip(recorder, recorder.image(STAMP, "cam", DEPTH_MM, "mono16"))
    with pytest.raises(ValueError, match="'mono16' is not supported"):
        images.image_color(message)
    with pytest.raises(ValueError, match="'mono16' is not supported"):
        images.image_depth(message)
    short = roundtrip(recorder, recorder.image(STAMP, "cam", RGB, "rgb8"))
    short.data = short.data[:10]
    with pytest.raises(ValueError, match="needs 15 bytes a row"):
        images.image_color(short)


def test_compressed_colour_jpeg_and_png(recorder: BagRecorder) -> None:
    smooth = cv2.resize(RGB, (40, 48), interpolation=cv2.INTER_CUBIC)
    png = recorder.compressed(STAMP, "cam", encode_png(smooth[:, :, ::-1]), "bgr8; png compressed bgr8")
    np.testing.assert_allclose(images.compressed_color(roundtrip(recorder, png)), smooth / 255.0, atol=1e-6)
    _, jpeg_data = cv2.imencode(".jpg", smooth[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 98])
    jpeg = recorder.compressed(STAMP, "cam", jpeg_data.tobytes(), "jpeg")
    assert np.abs(images.compressed_color(roundtrip(recorder, jpeg)) - smooth / 255.0).mean() < 0.02
    broken = recorder.compressed(STAMP, "cam", b"not an image", "jpeg")
    with pytest.raises(ValueError, match=r"compressed colour image \('jpeg'\) is neither a JPEG nor a PNG"):
        images.compressed_color(roundtrip(recorder, broken))


def test_compressed_depth_16uc1_png(recorder: BagRecorder) -> None:
    message = recorder.compressed(STAMP, "cam", compressed_depth_16(DEPTH_MM), "16UC1; compressedDepth png")
    np.testing.assert_allclose(images.compressed_depth(roundtrip(recorder, message)), DEPTH_MM / 1000.0, atol=1e-6)


def test_compressed_plugin_16uc1_png(recorder: BagRecorder) -> None:
    """image_transport's plain "compressed" plugin on 16UC1: a 16-bit PNG without compressedDepth's header."""
    message = recorder.compressed(STAMP, "cam", encode_png(DEPTH_MM), "16UC1; png compressed ")
    np.testing.assert_allclose(images.compressed_depth(roundtrip(recorder, message)), DEPTH_MM / 1000.0, atol=1e-6)


def test_image_topics_are_told_apart_by_their_first_message(recorder: BagRecorder) -> None:
    from ogmapping.datasets.rosbag.topics import COMPRESSED, IMAGE, image_kind

    kinds = {
        "rgb8": image_kind(IMAGE, recorder.image(STAMP, "cam", RGB, "rgb8")),
        "mono8": image_kind(IMAGE, recorder.image(STAMP, "cam", RGB[:, :, 0], "mono8")),
        "16UC1": image_kind(IMAGE, recorder.image(STAMP, "cam", DEPTH_MM, "16UC1")),
        "mono16 (IR)": image_kind(IMAGE, recorder.image(STAMP, "cam", DEPTH_MM, "mono16")),
        "jpeg": image_kind(COMPRESSED, recorder.compressed(STAMP, "cam", b"", "rgb8; jpeg compressed bgr8")),
        "compressedDepth": image_kind(COMPRESSED, recorder.compressed(STAMP, "cam", b"", "32FC1; compressedDepth")),
        "16UC1 png": image_kind(COMPRESSED, recorder.compressed(STAMP, "cam", b"", "16UC1; png compressed ")),
        "empty topic": image_kind(IMAGE, None),
    }
    assert kinds == {"rgb8": "color", "mono8": "color", "16UC1": "depth", "mono16 (IR)": None, "jpeg": "color",
                     "compressedDepth": "depth", "16UC1 png": "depth", "empty topic": None}


def test_compressed_depth_32fc1_inverse_depth(recorder: BagRecorder) -> None:
    metres = (DEPTH_MM / 1000.0).astype(np.float32)
    metres[0, 0] = np.nan
    message = recorder.compressed(STAMP, "cam", compressed_depth_32(metres), "32FC1; compressedDepth")
    depth = images.compressed_depth(roundtrip(recorder, message))
    assert depth[0, 0] == 0.0
    # The quantisation step grows as depth squared: ~1 mm at 1 m, ~2.5 cm at 5 m with these settings.
    np.testing.assert_allclose(depth[1:], metres[1:], rtol=0.006)


def test_compressed_depth_refusals(recorder: BagRecorder) -> None:
    rvl = recorder.compressed(STAMP, "cam", b"\0" * 20, "16UC1; compressedDepth rvl")
    with pytest.raises(ValueError, match="RVL"):
        images.compressed_depth(roundtrip(recorder, rvl))
    plain = recorder.compressed(STAMP, "cam", encode_png(RGB), "png")
    with pytest.raises(ValueError, match="compressedDepth"):
        images.compressed_depth(roundtrip(recorder, plain))
    colour_png = recorder.compressed(STAMP, "cam", b"\0" * 12 + encode_png(RGB), "16UC1; compressedDepth png")
    with pytest.raises(ValueError, match="one 16-bit channel"):
        images.compressed_depth(roundtrip(recorder, colour_png))


def test_camera_info_intrinsics_get_half_a_pixel(recorder: BagRecorder) -> None:
    info = roundtrip(recorder, recorder.camera_info(STAMP, "cam", 640, 480, (525.0, 524.0, 319.5, 239.5)))
    calibration = Calibration.from_message(info)
    k = calibration.intrinsics()
    assert (k.fx, k.fy, k.cx, k.cy, k.width, k.height) == (525.0, 524.0, 320.0, 240.0, 640, 480)
    assert calibration.undistortion_maps() is None
    assert "no distortion" in calibration.describe()


def test_unsupported_distortion_model_is_refused(recorder: BagRecorder) -> None:
    info = roundtrip(recorder, recorder.camera_info(STAMP, "cam", 64, 48, (50.0, 50.0, 32.0, 24.0),
                                                    model="equidistant", distortion=(0.1, 0.0, 0.0, 0.0)))
    with pytest.raises(ValueError, match=r"'equidistant'.*not supported"):
        Calibration.from_message(info)
    zero = roundtrip(recorder, recorder.camera_info(STAMP, "cam", 64, 48, (50.0, 50.0, 32.0, 24.0), model="equidistant",
                                                    distortion=(0.0,) * 4))
    assert not Calibration.from_message(zero).distorted


def test_binned_or_cropped_camera_info_is_refused(recorder: BagRecorder) -> None:
    info = roundtrip(recorder, recorder.camera_info(STAMP, "cam", 64, 48, (50.0, 50.0, 32.0, 24.0)))
    info.binning_x = 2
    with pytest.raises(ValueError, match="binning 2x0 is not supported"):
        Calibration.from_message(info)
    info.binning_x = 1
    info.roi.width, info.roi.height = 64, 48
    assert Calibration.from_message(info).width == 64  # the whole image as its region: fine
    info.roi.x_offset, info.roi.width = 8, 32
    with pytest.raises(ValueError, match=r"region of interest \(8, 0, 32, 48\)"):
        Calibration.from_message(info)


@pytest.mark.parametrize("model, coefficients", [
    ("plumb_bob", (-0.12, 0.03, 0.001, -0.0015, 0.0)),
    ("rational_polynomial", (-0.1, 0.02, 0.001, 0.0005, 0.0, 0.01, -0.005, 0.002)),
])
def test_distorted_images_are_undistorted(recorder: BagRecorder, model: str, coefficients: tuple) -> None:
    """A smooth image seen through a distorting lens comes back as the pinhole (P) image, away from the border."""
    width, height, k = 160, 120, (140.0, 138.0, 79.5, 59.5)
    info = roundtrip(recorder, recorder.camera_info(STAMP, "cam", width, height, k, model, coefficients))
    calibration = Calibration.from_message(info)
    assert calibration.distorted and model in calibration.describe()
    v, u = np.mgrid[0:height, 0:width].astype(np.float32)
    pinhole = np.dstack([0.5 + 0.4 * np.sin(u / 13.0), 0.5 + 0.4 * np.cos(v / 11.0), (u + v) / (width + height)])
    # The recorded image: each distorted pixel shows the pinhole pixel its ray goes through.
    camera = np.array([[k[0], 0, k[2]], [0, k[1], k[3]], [0, 0, 1]])
    rays = cv2.undistortPoints(np.dstack([u, v]).reshape(-1, 1, 2), camera, np.array(coefficients), P=camera)
    source = rays.reshape(height, width, 2).astype(np.float32)
    recorded = cv2.remap(pinhole.astype(np.float32), source[:, :, 0], source[:, :, 1], cv2.INTER_LINEAR)
    restored = undistort(recorded, calibration.undistortion_maps(), nearest=False)
    inner = (slice(20, -20), slice(25, -25))
    assert np.abs(restored[inner] - pinhole[inner]).max() < 0.02
    depth = np.full((height, width), 2.0, np.float32)
    depth[:, width // 2:] = 3.0
    restored_depth = undistort(depth, calibration.undistortion_maps(), nearest=True)
    assert set(np.unique(restored_depth)) <= {0.0, 2.0, 3.0}  # nearest neighbour: no blended depth


def _about_z(angle: float, translation: tuple[float, float, float]) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    pose = np.eye(4)
    pose[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    pose[:3, 3] = translation
    return pose


def _quaternion_z(angle: float) -> tuple[float, float, float, float]:
    return 0.0, 0.0, float(np.sin(angle / 2)), float(np.cos(angle / 2))


def test_track_interpolates_like_tf2_and_reaches_only_within_tolerance() -> None:
    track = Track("odom", "base")
    for second, angle in ((1, 0.0), (2, 1.0), (4, 3.0)):
        track.add(second * 10**9, (second * 1.0, 0.0, 0.0), _quaternion_z(angle))
    # Constant rate about a fixed axis: slerp and lerp are exact.
    np.testing.assert_allclose(track.at(1_250_000_000, 0), _about_z(0.25, (1.25, 0, 0)), atol=1e-12)
    np.testing.assert_allclose(track.at(3 * 10**9, 0), _about_z(2.0, (3.0, 0, 0)), atol=1e-12)
    np.testing.assert_allclose(track.at(4 * 10**9, 0), _about_z(3.0, (4.0, 0, 0)), atol=1e-12)
    assert track.at(4 * 10**9 + 1, 0) is None and track.at(10**9 - 1, 0) is None
    np.testing.assert_allclose(track.at(4_040_000_000, 50_000_000), _about_z(3.0, (4.0, 0, 0)), atol=1e-12)
    static = Track("base", "camera", static=True)
    static.add(5, (0.1, 0.0, 0.0), _quaternion_z(0.5))
    np.testing.assert_allclose(static.at(10**18, 0), _about_z(0.5, (0.1, 0, 0)), atol=1e-12)


def test_track_takes_the_short_way_round() -> None:
    track = Track("a", "b")
    track.add(0, (0.0, 0.0, 0.0), _quaternion_z(0.1))
    x, y, z, w = _quaternion_z(0.3)
    track.add(10, (0.0, 0.0, 0.0), (-x, -y, -z, -w))  # the same rotation, other sign
    np.testing.assert_allclose(track.at(5, 0), _about_z(0.2, (0, 0, 0)), atol=1e-12)


def test_tree_composes_a_chain_through_the_common_ancestor() -> None:
    tree = TransformTree()
    world_odom = _about_z(0.3, (1.0, 2.0, 0.0))
    # a camera_link -> optical rotation
    mount = quaternion_pose(np.array([0.2, 0.0, 0.5]), np.array([-0.5, 0.5, -0.5, 0.5]))
    tree.add("world", "odom", 0, tuple(world_odom[:3, 3]), _quaternion_z(0.3), static=True)
    tree.add("base", "cam", 0, tuple(mount[:3, 3]), (-0.5, 0.5, -0.5, 0.5), static=True)
    for second in (0, 2):
        tree.add("odom", "base", second * 10**9, (second * 1.0, 0.0, 0.0), _quaternion_z(second * 0.5), static=False)
    tree.add("world", "marker", 0, (0.0, 5.0, 0.0), (0.0, 0.0, 0.0, 1.0), static=True)
    expected = world_odom @ _about_z(0.5, (1.0, 0, 0)) @ mount
    np.testing.assert_allclose(tree.lookup("world", "cam", 10**9, 0), expected, atol=1e-12)
    marker = np.eye(4)
    marker[1, 3] = 5.0
    np.testing.assert_allclose(tree.lookup("marker", "cam", 10**9, 0), np.linalg.inv(marker) @ expected, atol=1e-12)
    assert tree.root("cam") == "world" and tree.moves("world", "cam") and not tree.moves("world", "marker")
    assert tree.lookup("world", "cam", 3 * 10**9, 0) is None  # beyond the moving edge's samples
    tree.add("elsewhere", "lonely", 0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), static=True)
    assert tree.lookup("world", "lonely", 0, 0) is None
    with pytest.raises(ValueError, match="two parents"):
        tree.add("world", "base", 0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), static=False)


def _stamped(topic: str, stamps_ms: list[int]) -> list[StampedImage]:
    return [StampedImage(MessageRef(topic, s, 0), STAMP + s * 1_000_000, "cam") for s in stamps_ms]


def test_pairing_is_one_to_one_within_the_tolerance() -> None:
    colors = _stamped("/c", [0, 33, 66, 100, 133])
    depths = _stamped("/d", [2, 30, 35, 101, 170])
    pairing = pair_images(colors, depths, 0.02)
    pairs = [(c.stamp_ns - STAMP) // 1_000_000 for c, _ in pairing.pairs]
    partners = [(d.stamp_ns - STAMP) // 1_000_000 for _, d in pairing.pairs]
    assert pairs == [0, 33, 100] and partners == [2, 35, 101]
    assert (pairing.unpaired_color, pairing.unpaired_depth) == (2, 2)
    assert len(pair_images(colors, depths, 0.002).pairs) == 3  # a pair exactly at the tolerance is kept
    assert len(pair_images(colors, depths, 0.0015).pairs) == 1
    assert pair_images(colors, depths, 0.0).pairs == []
    with pytest.raises(ValueError, match="pair-tolerance"):
        pair_images(colors, depths, -1.0)
