"""ROS bags written here with ``rosbags`` (ROS 1, ROS 2 MCAP and sqlite3) read back as the frames, poses and
calibration that went in: every image encoding, every pose source, the choice of topics, and the refusals."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

pytest.importorskip("rosbags")

from rosbag_writer import BagRecorder, compressed_depth_16, compressed_depth_32, encode_png

from ogmapping.datasets import detect_format, open_dataset
from ogmapping.datasets.base import opencv_intrinsics
from ogmapping.datasets.rosbag.topics import BagTopicError
from ogmapping.datasets.rosbag.transforms import invert
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.frames.rotation import quaternion_pose

T0 = 1_700_000_000 * 10**9
PERIOD = 33_333_333
OPTICAL = (-0.5, 0.5, -0.5, 0.5)  # camera_link (x forward, z up) -> optical frame (z forward, y down)
N = 4


def stamp(i: int) -> int:
    return T0 + i * PERIOD


@pytest.fixture(scope="module")
def frames():
    return [SyntheticSource(n_frames=N, width=48, height=36)[i] for i in range(N)]


def rgb8(frame) -> np.ndarray:
    return (frame.rgb * 255.0).round().astype(np.uint8)


def depth_mm(frame) -> np.ndarray:
    return (frame.depth * 1000.0).round().astype(np.uint16)


def published_k(frame) -> tuple[float, float, float, float]:
    """The frame's intrinsics as CameraInfo publishes them (integer pixel centres)."""
    k = frame.color_intrinsics
    return k.fx, k.fy, k.cx - 0.5, k.cy - 0.5


def base_motion(t_ns: int) -> np.ndarray:
    """odom -> base_link: a constant turn and drive, so TF's interpolation between samples is exact."""
    seconds = (t_ns - T0) * 1e-9
    angle = 0.4 * seconds
    return quaternion_pose(np.array([0.5 * seconds, 0.1 * seconds, 0.0]),
                 np.array([0.0, 0.0, np.sin(angle / 2), np.cos(angle / 2)]))


WORLD_ODOM = quaternion_pose(np.array([1.0, -2.0, 0.0]), np.array([0.0, 0.0, np.sin(0.15), np.cos(0.15)]))
BASE_LINK = quaternion_pose(np.array([0.2, 0.0, 1.1]), np.array([0.0, 0.0, 0.0, 1.0]))
LINK_OPTICAL = quaternion_pose(np.zeros(3), np.array(OPTICAL))


def write_frames(bag: BagRecorder, frames, i: int, color: str, depth: str,
                 color_frame: str = "camera_color_optical_frame", depth_frame: str | None = None,
                 depth_offset_ns: int = 0) -> None:
    """Frame i on /camera/color/... and /camera/depth/... in the named encodings, with camera_info beside colour."""
    frame, t = frames[i], stamp(i)
    depth_frame = depth_frame or color_frame
    k = published_k(frame)
    height, width = frame.depth.shape
    colour_message = {
        "rgb8": lambda: bag.image(t, color_frame, rgb8(frame), "rgb8"),
        "bgra8": lambda: bag.image(t, color_frame, cv2.cvtColor(rgb8(frame), cv2.COLOR_RGB2BGRA), "bgra8"),
        "jpeg": lambda: bag.compressed(t, color_frame, cv2.imencode(".jpg", rgb8(frame)[:, :, ::-1],
                                                                    [cv2.IMWRITE_JPEG_QUALITY, 97])[1].tobytes(),
                                       "rgb8; jpeg compressed bgr8"),
        "png": lambda: bag.compressed(t, color_frame, encode_png(rgb8(frame)[:, :, ::-1]), "rgb8; png compressed bgr8"),
    }[color]()
    suffix = "/compressed" if color in ("jpeg", "png") else ""
    bag.write(f"/camera/color/image_raw{suffix}", t, colour_message)
    bag.write("/camera/color/camera_info", t, bag.camera_info(t, color_frame, width, height, k))
    td = t + depth_offset_ns
    depth_message = {
        "16UC1": lambda: bag.image(td, depth_frame, depth_mm(frame), "16UC1"),
        "32FC1": lambda: bag.image(td, depth_frame, frame.depth.astype(np.float32), "32FC1"),
        "compressed16": lambda: bag.compressed(td, depth_frame, compressed_depth_16(depth_mm(frame)),
                                               "16UC1; compressedDepth png"),
        "compressed32": lambda: bag.compressed(td, depth_frame, compressed_depth_32(frame.depth),
                                               "32FC1; compressedDepth png"),
    }[depth]()
    suffix = "/compressedDepth" if depth.startswith("compressed") else ""
    bag.write(f"/camera/depth/image_raw{suffix}", td, depth_message)


def assert_images(read, frame, color: str, depth: str) -> None:
    colour_error = np.abs(read.rgb - rgb8(frame) / 255.0)
    assert colour_error.mean() < 0.03 if color == "jpeg" else colour_error.max() < 1e-6
    expected = {"16UC1": depth_mm(frame) / 1000.0, "compressed16": depth_mm(frame) / 1000.0,
                "32FC1": frame.depth, "compressed32": frame.depth}[depth]
    np.testing.assert_allclose(read.depth, expected, rtol=3e-3 if depth == "compressed32" else 1e-6)


def test_ros1_tf_chain_interpolated_at_the_image_stamps(tmp_path: Path, frames) -> None:
    """world -> odom (static) -> base_link (moving, sampled at 40 Hz off the image clock) -> camera_link ->
    camera_color_optical_frame (static): the camera's pose at each image stamp is the chain composed there."""
    path = tmp_path / "robot.bag"
    with BagRecorder(path, ros2=False) as bag:
        static = bag.tf(T0, [("world", "odom", WORLD_ODOM), ("base_link", "camera_link", BASE_LINK),
                             ("camera_link", "camera_color_optical_frame", LINK_OPTICAL)])
        bag.write("/tf_static", T0 - 10**8, static)
        for sample in range(-4, 8):
            t = T0 + sample * 25_000_000
            bag.write("/tf", t, bag.tf(t, [("odom", "base_link", base_motion(t))]))
        for i in range(N):
            write_frames(bag, frames, i, "rgb8", "16UC1")
    assert detect_format(path) == "bag"
    source = open_dataset(str(path))
    assert len(source) == N
    for i in range(N):
        read = source[i]
        expected = WORLD_ODOM @ base_motion(stamp(i)) @ BASE_LINK @ LINK_OPTICAL
        np.testing.assert_allclose(read.c2w, expected, atol=1e-9)
        assert read.timestamp == pytest.approx(stamp(i) * 1e-9, abs=1e-6)
        assert read.color_intrinsics == frames[i].color_intrinsics and read.registered
        assert_images(read, frames[i], "rgb8", "16UC1")
    report = "\n".join(source.report())
    assert "TF, camera_color_optical_frame in world" in report and "odom -> base_link -> camera_link" in report
    # A fixed frame other than the root: poses of the camera in odom.
    in_odom = open_dataset(str(path), "bag", fixed_frame="odom")
    np.testing.assert_allclose(in_odom[0].c2w, invert(WORLD_ODOM) @ source[0].c2w, atol=1e-9)


def test_ros2_mcap_compressed_images_and_a_pose_topic(tmp_path: Path, frames) -> None:
    """JPEG colour and compressedDepth PNG, a PoseStamped of the camera, a depth camera of its own, other topics."""
    path = tmp_path / "robot"  # ros2 bag record's folder: metadata.yaml and robot.mcap
    with BagRecorder(path, ros2=True) as bag:
        for i in range(N):
            write_frames(bag, frames, i, "jpeg", "compressed16")
            bag.write("/camera_pose", stamp(i), bag.pose_stamped(stamp(i), "map", frames[i].c2w))
            info = bag.camera_info(stamp(i), "camera_color_optical_frame", 48, 36, published_k(frames[i]))
            bag.write("/camera/depth/camera_info", stamp(i), info)
            bag.write("/rosout_agg", stamp(i), bag.t("std_msgs/msg/String")(data="hello"))
    source = open_dataset(str(path))
    assert len(source) == N
    for i in range(N):
        read = source[i]
        np.testing.assert_allclose(read.c2w, frames[i].c2w, atol=1e-9)
        assert_images(read, frames[i], "jpeg", "compressed16")
    assert "/camera_pose (geometry_msgs/msg/PoseStamped)" in "\n".join(source.report())
    alone = path / "robot.mcap"  # the storage file without its metadata.yaml reads the same
    assert detect_format(alone) == "bag"
    np.testing.assert_array_equal(open_dataset(str(alone))[N - 1].depth, source[N - 1].depth)


def test_ros2_sqlite_odometry_mounted_by_tf_and_depth_from_its_own_camera(tmp_path: Path, frames) -> None:
    """Odometry gives base_link in odom, /tf_static mounts the colour camera on it and the depth camera 5 cm to
    the side; depth runs 4 ms behind colour and misses a frame, which is dropped and counted."""
    path = tmp_path / "robot_db3"
    colour_in_depth = quaternion_pose(np.array([0.05, 0.0, 0.0]), np.array([0.0, 0.0, 0.0, 1.0]))
    with BagRecorder(path, ros2=True, storage="sqlite3") as bag:
        bag.write("/tf_static", T0, bag.tf(T0, [
            ("base_link", "camera_color_optical_frame", BASE_LINK @ LINK_OPTICAL),
            ("camera_color_optical_frame", "camera_depth_optical_frame", invert(colour_in_depth))]))
        for i in range(N):
            if i == 2:
                t = stamp(i)
                bag.write("/camera/color/image_raw", t,
                          bag.image(t, "camera_color_optical_frame", cv2.cvtColor(rgb8(frames[i]), cv2.COLOR_RGB2BGRA),
                                    "bgra8"))
            else:
                write_frames(bag, frames, i, "bgra8", "32FC1", depth_frame="camera_depth_optical_frame",
                             depth_offset_ns=4_000_000)
            body = frames[i].c2w @ invert(BASE_LINK @ LINK_OPTICAL)
            bag.write("/odom", stamp(i), bag.odometry(stamp(i), "odom", "base_link", body))
    assert (path / "metadata.yaml").is_file()
    source = open_dataset(str(path))
    assert len(source) == N - 1
    for read, i in zip(source, (0, 1, 3), strict=True):
        np.testing.assert_allclose(read.c2w, frames[i].c2w, atol=1e-9)
        np.testing.assert_allclose(read.depth_to_color, invert(colour_in_depth), atol=1e-12)
        assert not read.registered
        assert_images(read, frames[i], "bgra8", "32FC1")
    report = "\n".join(source.report())
    assert "1 colour images without depth" in report and "base_link in odom, through TF" in report
    assert "registered onto 'camera_color_optical_frame' through TF" in report


def test_ros1_png_colour_compressed_32fc1_depth_and_a_covariance_pose(tmp_path: Path, frames) -> None:
    path = tmp_path / "robot.bag"
    with BagRecorder(path, ros2=False) as bag:
        for i in range(N):
            write_frames(bag, frames, i, "png", "compressed32")
            pose = bag.t("geometry_msgs/msg/PoseWithCovarianceStamped")(
                header=bag.header(stamp(i), "map"),
                pose=bag.t("geometry_msgs/msg/PoseWithCovariance")(pose=bag._pose(frames[i].c2w),
                                                                  covariance=np.zeros(36)))
            bag.write("/amcl_pose", stamp(i), pose)
    source = open_dataset(str(path))
    for i in range(N):
        np.testing.assert_allclose(source[i].c2w, frames[i].c2w, atol=1e-9)
        assert_images(source[i], frames[i], "png", "compressed32")


def test_distortion_is_reported_and_removed(tmp_path: Path, frames) -> None:
    path = tmp_path / "robot.mcap"
    distortion = (-0.05, 0.01, 0.0, 0.0, 0.0)
    with BagRecorder(path, ros2=True) as bag:
        for i in range(2):
            t = stamp(i)
            bag.write("/cam/image", t, bag.image(t, "cam_optical_frame", rgb8(frames[i]), "rgb8"))
            bag.write("/cam/depth", t, bag.image(t, "cam_optical_frame", depth_mm(frames[i]), "16UC1"))
            bag.write("/cam/camera_info", t, bag.camera_info(t, "cam_optical_frame", 48, 36, published_k(frames[i]),
                                                             "plumb_bob", distortion))
            bag.write("/pose", t, bag.pose_stamped(t, "map", frames[i].c2w))
    source = open_dataset(str(path))
    assert "plumb_bob distortion [-0.05, 0.01, 0.0, 0.0, 0.0] removed" in "\n".join(source.report())
    k = published_k(frames[0])
    camera = np.array([[k[0], 0, k[2]], [0, k[1], k[3]], [0, 0, 1]])
    maps = cv2.initUndistortRectifyMap(camera, np.array(distortion), None, camera, (48, 36), cv2.CV_32FC1)
    expected = cv2.remap(rgb8(frames[0]).astype(np.float32) / 255.0, *maps, cv2.INTER_LINEAR)
    np.testing.assert_allclose(source[0].rgb, expected, atol=1e-5)
    assert source[0].color_intrinsics == opencv_intrinsics(*k, 48, 36)


def write_seven_scenes(folder: Path, frames) -> None:
    """The frames as a 7-Scenes folder: PNG colour, millimetre PNG depth, pose text files, the depth K."""
    folder.mkdir()
    fx, fy, cx, cy = published_k(frames[0])
    np.savetxt(folder / "camera-intrinsics.txt", [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], fmt="%.17g")
    for i, frame in enumerate(frames):
        cv2.imwrite(str(folder / f"frame-{i:06d}.color.png"), rgb8(frame)[:, :, ::-1])
        cv2.imwrite(str(folder / f"frame-{i:06d}.depth.png"), depth_mm(frame))
        np.savetxt(folder / f"frame-{i:06d}.pose.txt", frame.c2w, fmt="%.17g")


def map_of(frames) -> dict:
    from ogmapping.config import resolve
    from ogmapping.mapper import Mapper

    overrides = {"keyframes.iterations": 2, "keyframes.first_iterations": 4, "refine.interval": 2,
                 "refine.min_observations": 1}
    mapper = Mapper(resolve("sparse", overrides=overrides))
    for frame in frames:
        mapper.process(frame)
    return mapper.state().tensors


def test_a_map_from_a_bag_equals_the_map_from_the_same_frames_read_directly(tmp_path: Path, frames) -> None:
    """The synthetic frames as a 7-Scenes folder and as a bag (TF poses, raw images): the same map.

    Poses pass through a quaternion in the bag, so they agree to 1e-15, not bit for bit; the maps agree
    to float32 rounding.
    """
    import torch

    frames = frames[:2]
    write_seven_scenes(tmp_path / "direct", frames)
    path = tmp_path / "robot.mcap"
    with BagRecorder(path, ros2=True) as bag:
        for i in range(len(frames)):
            write_frames(bag, frames, i, "rgb8", "16UC1")
            bag.write("/tf", stamp(i), bag.tf(stamp(i), [("map", "camera_color_optical_frame", frames[i].c2w)]))
    direct = list(open_dataset(str(tmp_path / "direct"), "7scenes", color_intrinsics=published_k(frames[0])))
    from_bag = list(open_dataset(str(path)))
    for read, reference in zip(from_bag, direct, strict=True):
        np.testing.assert_array_equal(read.rgb, reference.rgb)
        np.testing.assert_array_equal(read.depth, reference.depth)
        assert (read.color_intrinsics, read.depth_intrinsics) == (reference.color_intrinsics,
                                                                   reference.depth_intrinsics)
        np.testing.assert_allclose(read.c2w, reference.c2w, rtol=0, atol=1e-15)
    maps = [map_of(direct), map_of(from_bag)]
    assert maps[0].keys() == maps[1].keys()
    for name, tensor in maps[0].items():
        torch.testing.assert_close(maps[1][name], tensor, rtol=1e-5, atol=1e-5, msg=name)


def write_two_colour_cameras(path: Path, frames) -> None:
    with BagRecorder(path, ros2=True) as bag:
        for i in range(2):
            write_frames(bag, frames, i, "rgb8", "16UC1")
            bag.write("/camera/ir/image_raw", stamp(i), bag.image(stamp(i), "ir", rgb8(frames[i])[:, :, 0], "mono8"))
            bag.write("/tf", stamp(i), bag.tf(stamp(i), [("map", "camera_color_optical_frame", frames[i].c2w)]))


def test_a_bag_that_does_not_fit_is_refused_with_its_topics(tmp_path: Path, frames) -> None:
    chatter = tmp_path / "chatter.bag"
    with BagRecorder(chatter, ros2=False) as bag:
        bag.write("/chatter", T0, bag.t("std_msgs/msg/String")(data="hi"))
    with pytest.raises(BagTopicError, match="no colour image topic") as refused:
        open_dataset(str(chatter))
    assert "/chatter  std_msgs/msg/String  (1 messages)" in str(refused.value)
    assert "--color-topic" in str(refused.value)

    two = tmp_path / "two.mcap"
    write_two_colour_cameras(two, frames)
    with pytest.raises(BagTopicError, match=r"2 colour image topics \(/camera/color/image_raw, /camera/ir/image_raw\)"):
        open_dataset(str(two))
    assert len(open_dataset(str(two), "bag", color_topic="/camera/color/image_raw")) == 2
    with pytest.raises(BagTopicError, match=r"--color-topic /camera/depth/image_raw .* does not hold colour image"):
        open_dataset(str(two), "bag", color_topic="/camera/depth/image_raw")
    with pytest.raises(BagTopicError, match="--depth-topic /nope is not in the bag"):
        open_dataset(str(two), "bag", color_topic="/camera/color/image_raw", depth_topic="/nope")


def test_pose_sources_must_be_one(tmp_path: Path, frames) -> None:
    static_only = tmp_path / "static.bag"
    with BagRecorder(static_only, ros2=False) as bag:
        bag.write("/tf_static", T0, bag.tf(T0, [("base_link", "camera_color_optical_frame", BASE_LINK)]))
        for i in range(2):
            write_frames(bag, frames, i, "rgb8", "16UC1")
    with pytest.raises(BagTopicError, match="need exactly one pose source, found none"):
        open_dataset(str(static_only))

    both = tmp_path / "both.mcap"
    with BagRecorder(both, ros2=True) as bag:
        for i in range(2):
            write_frames(bag, frames, i, "rgb8", "16UC1")
            bag.write("/tf", stamp(i), bag.tf(stamp(i), [("map", "camera_color_optical_frame", frames[i].c2w)]))
            bag.write("/odom", stamp(i), bag.odometry(stamp(i), "odom", "base_link", frames[i].c2w))
    with pytest.raises(BagTopicError, match=r"found TF \(map -> camera_color_optical_frame\), /odom"):
        open_dataset(str(both))
    np.testing.assert_allclose(open_dataset(str(both), "bag", fixed_frame="map")[1].c2w, frames[1].c2w, atol=1e-9)
    with pytest.raises(BagTopicError, match="gives the pose of 'base_link' but TF has no chain"):
        open_dataset(str(both), "bag", pose_topic="/odom")
    camera_odometry = open_dataset(str(both), "bag", pose_topic="/odom", body_frame="camera_color_optical_frame")
    np.testing.assert_allclose(camera_odometry[1].c2w, frames[1].c2w, atol=1e-9)
    with pytest.raises(ValueError, match="two pose sources"):
        open_dataset(str(both), "bag", pose_topic="/odom", fixed_frame="map")
    with pytest.raises(BagTopicError, match="fixed frame 'nowhere' is not in TF"):
        open_dataset(str(both), "bag", fixed_frame="nowhere")


def test_images_beyond_the_poses_are_dropped(tmp_path: Path, frames) -> None:
    path = tmp_path / "late.mcap"
    with BagRecorder(path, ros2=True) as bag:
        for i in range(N):
            write_frames(bag, frames, i, "rgb8", "16UC1")
        for i in (1, 2):
            bag.write("/pose", stamp(i), bag.pose_stamped(stamp(i), "map", frames[i].c2w))
    source = open_dataset(str(path), "bag", pose_tolerance=0.02)
    assert [f.timestamp for f in source] == pytest.approx([stamp(1) * 1e-9, stamp(2) * 1e-9], abs=1e-6)
    assert "2 pairs without a pose within 0.02 s" in "\n".join(source.report())
    assert len(open_dataset(str(path))) == N  # 33 ms beyond the ends is within the default 50 ms

    later = tmp_path / "later.mcap"
    with BagRecorder(later, ros2=True) as bag:
        for i in range(2):
            write_frames(bag, frames, i, "rgb8", "16UC1")
            bag.write("/pose", stamp(i) + 10**10, bag.pose_stamped(stamp(i) + 10**10, "map", frames[i].c2w))
    with pytest.raises(ValueError, match=r"2 pairs within 0\.02 s, none with a pose from /pose"):
        open_dataset(str(later))


@pytest.mark.realdata
def test_seven_scenes_frames_through_a_ros1_bag(tmp_path: Path, seven_scenes: Path) -> None:
    """Real 7-Scenes frames with their colour and depth cameras' own CameraInfo and optical frames (as a Kinect
    driver publishes them) and TF poses read back as the 7-Scenes reader reads them: same pixels, intrinsics,
    poses and depth-to-colour transform."""
    from ogmapping.datasets.sevenscenes import MEASURED_COLOR_K, SevenScenes

    reference = SevenScenes(seven_scenes)
    count = 5
    depth_k = reference.depth_intrinsics
    path = tmp_path / "kitchen.bag"
    with BagRecorder(path, ros2=False) as bag:
        for i in range(count):
            frame, t = reference[i], stamp(i)
            rgb = (frame.rgb * 255.0).round().astype(np.uint8)
            depth = (frame.depth * 1000.0).round().astype(np.uint16)
            bag.write("/camera/rgb/image_color", t, bag.image(t, "camera_rgb_optical_frame", rgb, "rgb8"))
            bag.write("/camera/rgb/camera_info", t, bag.camera_info(t, "camera_rgb_optical_frame", 640, 480,
                                                                    MEASURED_COLOR_K))
            bag.write("/camera/depth/image_raw", t + 1_000_000, bag.image(t + 1_000_000, "camera_depth_optical_frame",
                                                                          depth, "16UC1"))
            published_depth_k = (depth_k.fx, depth_k.fy, depth_k.cx - 0.5, depth_k.cy - 0.5)
            bag.write("/camera/depth/camera_info", t,
                      bag.camera_info(t, "camera_depth_optical_frame", 640, 480, published_depth_k))
            bag.write("/tf", t, bag.tf(t, [("world", "camera_rgb_optical_frame", frame.c2w),
                                           ("camera_rgb_optical_frame", "camera_depth_optical_frame",
                                            frame.depth_to_color)]))
    source = open_dataset(str(path))
    assert len(source) == count
    for i in range(count):
        read, expected = source[i], reference[i]
        np.testing.assert_array_equal(read.rgb, expected.rgb)
        np.testing.assert_array_equal(read.depth, expected.depth)
        assert read.color_intrinsics == expected.color_intrinsics
        assert read.depth_intrinsics == expected.depth_intrinsics
        np.testing.assert_allclose(read.depth_to_color, expected.depth_to_color, atol=1e-12)
        # 7-Scenes rotations are orthonormal to ~1e-4 only; a quaternion carries the nearest rotation.
        np.testing.assert_allclose(read.c2w[:3, 3], expected.c2w[:3, 3], atol=1e-12)
        np.testing.assert_allclose(read.c2w[:3, :3], expected.c2w[:3, :3], atol=2e-4)


def test_depth_of_another_size_needs_its_own_camera_info(tmp_path: Path, frames) -> None:
    """Half-resolution depth with only the colour camera's CameraInfo is refused naming the flag; with its own
    CameraInfo it is a depth camera of its own, registered onto colour like any dataset's."""
    from ogmapping.frames.preprocess import register_depth

    for with_info in (False, True):
        path = tmp_path / f"half_{with_info}.mcap"
        with BagRecorder(path, ros2=True) as bag:
            for i in range(2):
                t = stamp(i)
                bag.write("/cam/color/image_raw", t, bag.image(t, "cam_optical_frame", rgb8(frames[i]), "rgb8"))
                bag.write("/cam/color/camera_info", t, bag.camera_info(t, "cam_optical_frame", 48, 36,
                                                                       published_k(frames[i])))
                half = depth_mm(frames[i])[::2, ::2]
                bag.write("/cam/depth/image_raw", t, bag.image(t, "cam_optical_frame", half, "16UC1"))
                if with_info:
                    fx, fy, cx, cy = published_k(frames[i])
                    bag.write("/cam/depth/camera_info", t, bag.camera_info(
                        t, "cam_optical_frame", 24, 18, (fx / 2, fy / 2, (cx + 0.5) / 2 - 0.5, (cy + 0.5) / 2 - 0.5)))
                bag.write("/pose", t, bag.pose_stamped(t, "map", frames[i].c2w))
        source = open_dataset(str(path))
        if not with_info:
            with pytest.raises(ValueError, match=r"image is 24x18 but its CameraInfo \(the colour camera's; name the "
                                                 r"depth camera's with --depth-info-topic\) says 48x36"):
                source[0]
            continue
        frame = source[0]
        assert frame.depth_intrinsics == frames[0].color_intrinsics.scaled(0.5) and not frame.registered
        registered = register_depth(frame)
        np.testing.assert_allclose(registered.depth[::2, ::2], depth_mm(frames[0])[::2, ::2] / 1000.0, atol=1e-6)


def test_images_without_a_frame_take_camera_frame(tmp_path: Path, frames) -> None:
    path = tmp_path / "anonymous.bag"
    with BagRecorder(path, ros2=False) as bag:
        for i in range(2):
            write_frames(bag, frames, i, "rgb8", "16UC1", color_frame="")
            bag.write("/tf", stamp(i), bag.tf(stamp(i), [("world", "head_camera", frames[i].c2w)]))
    with pytest.raises(BagTopicError, match=r"have no header\.frame_id; pass --camera-frame"):
        open_dataset(str(path))
    source = open_dataset(str(path), "bag", camera_frame="head_camera")
    np.testing.assert_allclose(source[1].c2w, frames[1].c2w, atol=1e-9)
    assert source[1].depth_to_color is None
    assert "camera frame 'head_camera' is not named *_optical_frame" in "\n".join(source.report())


def test_images_without_stamps_take_the_bag_time(tmp_path: Path, frames) -> None:
    """Some drivers leave header.stamp at zero: the recorder's receive time is then the only clock."""
    path = tmp_path / "unstamped.mcap"
    with BagRecorder(path, ros2=True) as bag:
        for i in range(3):
            t = stamp(i)
            bag.write("/cam/image", t, bag.image(0, "cam_optical_frame", rgb8(frames[i]), "rgb8"))
            bag.write("/cam/depth", t + 2_000_000, bag.image(0, "cam_optical_frame", depth_mm(frames[i]), "16UC1"))
            bag.write("/cam/camera_info", t, bag.camera_info(t, "cam_optical_frame", 48, 36, published_k(frames[i])))
            bag.write("/pose", t, bag.pose_stamped(t, "map", frames[i].c2w))
    source = open_dataset(str(path))
    assert [f.timestamp for f in source] == pytest.approx([stamp(i) * 1e-9 for i in range(3)], abs=1e-6)
    np.testing.assert_allclose(source[2].c2w, frames[2].c2w, atol=1e-9)
    assert_images(source[2], frames[2], "rgb8", "16UC1")
    assert "/cam/image has no header stamps: the bag's receive times stand in" in "\n".join(source.report())
