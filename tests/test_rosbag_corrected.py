"""A SLAM system's corrected trajectory read from a topic of the bag (``--corrected-topic``): a Path's last
message or a stream of pose messages, converted as the frames' poses are (a correction equal to a frame's pose
is that pose), keyed by the frames' timestamps; and the refusals, each naming the topic."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")

from ogclient.__main__ import parser as client_parser
from rosbag_writer import BagRecorder
from test_rosbag_reader import BASE_LINK, LINK_OPTICAL, T0, N, stamp, write_frames

from ogmapping.cli.options import open_frame_set
from ogmapping.datasets import open_dataset
from ogmapping.datasets.rosbag.topics import BagTopicError
from ogmapping.datasets.rosbag.transforms import invert
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.frames.rotation import quaternion_pose

CAMERA = "camera_color_optical_frame"
MOUNT = BASE_LINK @ LINK_OPTICAL  # base_link -> the camera, on /tf_static
LOOP = quaternion_pose(np.array([0.04, -0.02, 0.0]), np.array([0.0, 0.0, np.sin(0.01), np.cos(0.01)]))
STALE = quaternion_pose(np.array([3.0, 0.0, 0.0]), np.array([0.0, 0.0, 0.0, 1.0]))

Corrections = Callable[[BagRecorder, list, int], None]  # writes the corrections that go with frame i


@pytest.fixture(scope="module")
def frames():
    return [SyntheticSource(n_frames=N, width=48, height=36)[i] for i in range(N)]


def body(frame) -> np.ndarray:
    """base_link in odom where the camera is at the frame's pose."""
    return frame.c2w @ invert(MOUNT)


def write_bag(path: Path, frames, corrections: Corrections) -> Path:
    """Frames whose poses are Odometry of base_link in odom, the camera mounted on it by /tf_static."""
    with BagRecorder(path, ros2=True) as bag:
        bag.write("/tf_static", T0, bag.tf(T0, [("base_link", CAMERA, MOUNT)]))
        for i in range(N):
            write_frames(bag, frames, i, "rgb8", "16UC1")
            bag.write("/odom", stamp(i), bag.odometry(stamp(i), "odom", "base_link", body(frames[i])))
            corrections(bag, frames, i)
    return path


def slam_path(bag: BagRecorder, frames, i: int) -> None:
    """A stale path after frame 1, then the corrected one of every frame after the last."""
    if i == 1:
        bag.write("/slam/path", stamp(i), bag.path(stamp(i), "odom", [(stamp(j), STALE) for j in range(2)]))
    if i == N - 1:
        poses = [(stamp(j), LOOP @ body(frames[j])) for j in range(N)]
        bag.write("/slam/path", stamp(i) + 1, bag.path(stamp(i) + 1, "odom", poses))


def slam_poses(bag: BagRecorder, frames, i: int) -> None:
    """A corrected PoseStamped of base_link (the pose source's body) a frame."""
    bag.write("/slam/path", stamp(i), bag.pose_stamped(stamp(i), "odom", LOOP @ body(frames[i])))


def slam_odometry(bag: BagRecorder, frames, i: int) -> None:
    """Odometry of the camera itself a frame, a stale one first at the same stamp."""
    bag.write("/slam/path", stamp(i), bag.odometry(stamp(i), "odom", CAMERA, STALE))
    bag.write("/slam/path", stamp(i) + 1, bag.odometry(stamp(i), "odom", CAMERA, LOOP @ frames[i].c2w))


@pytest.mark.parametrize(("corrections", "described"), [
    (slam_path, "(nav_msgs/msg/Path, the last of 2 messages): 4 poses of base_link in odom, through TF "
                f"base_link -> {CAMERA}"),
    (slam_poses, "(geometry_msgs/msg/PoseStamped, 4 messages): 4 poses of base_link in odom, through TF"),
    (slam_odometry, f"(nav_msgs/msg/Odometry, 8 messages): 4 poses of {CAMERA} in odom"),
])
def test_corrected_poses_are_the_cameras_keyed_by_the_frames_timestamps(tmp_path: Path, frames,
                                                                       corrections: Corrections,
                                                                       described: str) -> None:
    path = write_bag(tmp_path / "robot.mcap", frames, corrections)
    source = open_dataset(str(path), "bag", corrected_topic="/slam/path")
    assert "poses: /odom (nav_msgs/msg/Odometry)" in "\n".join(source.report())  # never the pose source
    assert f"corrected poses: /slam/path {described}" in "\n".join(source.report())
    assert source.corrected is not None and source.corrected.name == "/slam/path"
    assert source.corrected.keys.tolist() == [source[i].timestamp for i in range(N)]
    for i in range(N):
        np.testing.assert_allclose(source[i].c2w, frames[i].c2w, atol=1e-9)
        np.testing.assert_allclose(source.corrected.find(source[i].timestamp), LOOP @ source[i].c2w, atol=1e-9)


def test_a_corrected_path_equal_to_the_pose_source_gives_the_frames_poses(tmp_path: Path, frames) -> None:
    def same(bag: BagRecorder, frames, i: int) -> None:
        if i == N - 1:
            bag.write("/slam/path", stamp(i), bag.path(stamp(i), "odom", [(stamp(j), body(frames[j]))
                                                                          for j in range(N)]))

    source = open_dataset(str(write_bag(tmp_path / "robot.mcap", frames, same)), "bag", corrected_topic="/slam/path")
    for i in range(N):
        np.testing.assert_allclose(source.corrected.find(source[i].timestamp), source[i].c2w, rtol=0, atol=1e-15)


def test_under_tf_a_path_gives_the_cameras_poses_unless_body_frame_names_its_body(tmp_path: Path, frames) -> None:
    """ROS 1, the camera's poses from TF (map -> base_link moving, the camera mounted on it): a Path in map is of
    the camera's optical frame as TF's poses are, or of the frame --body-frame names."""
    path = tmp_path / "robot.bag"
    with BagRecorder(path, ros2=False) as bag:
        bag.write("/tf_static", T0, bag.tf(T0, [("base_link", CAMERA, MOUNT)]))
        for i in range(N):
            write_frames(bag, frames, i, "rgb8", "16UC1")
            bag.write("/tf", stamp(i), bag.tf(stamp(i), [("map", "base_link", body(frames[i]))]))
        last = stamp(N - 1)
        bag.write("/slam/path", last, bag.path(last, "map", [(stamp(j), LOOP @ body(frames[j])) for j in range(N)]))
    mounted = open_dataset(str(path), "bag", corrected_topic="/slam/path", body_frame="base_link")
    as_camera = open_dataset(str(path), "bag", corrected_topic="/slam/path")
    assert f"4 poses of {CAMERA} in map" in "\n".join(as_camera.report())
    for i in range(N):
        key = mounted[i].timestamp
        np.testing.assert_allclose(mounted.corrected.find(key), LOOP @ mounted[i].c2w, atol=1e-9)
        np.testing.assert_allclose(as_camera.corrected.find(key), LOOP @ body(frames[i]), atol=1e-9)


def awkward_topics(bag: BagRecorder, frames, i: int) -> None:
    """A String topic, a pose topic with no messages, a path in another world frame, a path ending empty."""
    if i == 0:
        bag.write("/chatter", stamp(i), bag.t("std_msgs/msg/String")(data="hi"))
        bag.write("/slam/cleared", stamp(i), bag.path(stamp(i), "odom", [(stamp(i), body(frames[i]))]))
        bag.write("/slam/cleared", stamp(i) + 1, bag.path(stamp(i) + 1, "odom", []))
        bag.connections["/empty"] = bag.writer.add_connection("/empty", "nav_msgs/msg/Path", typestore=bag.store)
        bag.write("/slam/map", stamp(i), bag.path(stamp(i), "map", [(stamp(i), body(frames[i]))]))


@pytest.fixture
def awkward(tmp_path: Path, frames) -> Path:
    return write_bag(tmp_path / "robot.mcap", frames, awkward_topics)


@pytest.mark.parametrize(("topic", "refusal"), [
    ("/nope", "--corrected-topic /nope is not in the bag"),
    ("/chatter", "--corrected-topic /chatter is a std_msgs/msg/String topic; a corrected trajectory is one of "
                 "nav_msgs/msg/Path, geometry_msgs/msg/PoseStamped"),
    ("/empty", r"--corrected-topic /empty \(nav_msgs/msg/Path\) has no messages"),
    ("/slam/map", "--corrected-topic /slam/map gives poses in 'map', the frames' poses are in 'odom'"),
    ("/slam/cleared", r"--corrected-topic /slam/cleared \(nav_msgs/msg/Path\): its last message holds no poses"),
    ("/odom", "--pose-topic and --corrected-topic both name /odom"),
])
def test_a_corrected_topic_that_does_not_fit_is_refused_when_the_bag_opens(awkward: Path, topic: str,
                                                                           refusal: str) -> None:
    with pytest.raises(ValueError, match=refusal) as refused:
        open_dataset(str(awkward), "bag", pose_topic="/odom", corrected_topic=topic)
    if topic != "/odom":
        assert isinstance(refused.value, BagTopicError) and "/chatter  std_msgs/msg/String" in str(refused.value)


def test_the_flag_goes_with_a_bag_and_not_with_corrected_trajectory(awkward: Path,
                                                                    capsys: pytest.CaptureFixture) -> None:
    args = client_parser().parse_args(["stream", "--bag", str(awkward), "--corrected-topic", "/chatter"])
    with pytest.raises(BagTopicError, match="/chatter is a std_msgs/msg/String topic"):
        open_frame_set(args)
    with pytest.raises(ValueError, match="--corrected-topic is for ROS bags; synthetic is not one"):
        open_frame_set(client_parser().parse_args(["stream", "--data", "synthetic", "--corrected-topic", "/p"]))
    with pytest.raises(SystemExit):
        client_parser().parse_args(["stream", "--bag", str(awkward), "--corrected-topic", "/slam/path",
                                    "--corrected-trajectory", "slam.tum"])
    assert "--corrected-trajectory: not allowed with argument --corrected-topic" in capsys.readouterr().err
