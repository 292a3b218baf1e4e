"""The tiny synthetic scene and session configurations every service test shares."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml
from ogapi.convert import FrameEncoding
from ogapi.v1 import mapping_pb2 as pb
from ogclient.messages import frame_to_proto

from ogmapping.quality.evaluation import FrameSet, open_frames

REPO = Path(__file__).resolve().parents[2]
TEST_SERVER_CONFIG = REPO / "docker" / "test-server.yaml"
LIMITS = yaml.safe_load(TEST_SERVER_CONFIG.read_text())["limits"]

PRESET = "sparse-fast"
# A few optimisation steps: the map learns something, a session maps in seconds on a CPU.
TINY = {"keyframes.first_iterations": "6", "keyframes.iterations": "2"}
# No optimisation at all: anchors are allocated but nothing is trained; for tests of plumbing.
FROZEN = {"keyframes.first_iterations": "0", "keyframes.iterations": "0"}
FRAMES = "0:10"  # 9 streamed positions, position 5 held out
SCALE = 0.25  # 320x240 -> 80x60


def scene(frames: str = FRAMES) -> FrameSet:
    return open_frames("synthetic", "synthetic", frames, 1, SCALE, n_frames=40)


def messages(frame_set: FrameSet, encoding: FrameEncoding | None = None) -> list[pb.Frame]:
    encoding = encoding or FrameEncoding()
    return [frame_to_proto(frame_set.load(p), encoding) for p in frame_set.selection.streamed]


def create_request(overrides: dict[str, str], label: str = "test") -> pb.CreateSessionRequest:
    return pb.CreateSessionRequest(preset=PRESET, overrides=overrides, label=label)


def write_ros_bag(path: Path, count: int, corrected: list[np.ndarray] | None = None) -> None:
    """The synthetic room as a ROS 2 bag (MCAP): raw rgb8 and 16UC1, camera_info, Odometry of the camera; with
    ``corrected``, a SLAM system's nav_msgs/Path of those camera poses (one a frame) after the last frame."""
    from rosbag_writer import BagRecorder

    frames = scene(f"0:{count}")
    stamps = [1_700_000_000 * 10**9 + i * 33_333_333 for i in range(count)]
    with BagRecorder(path, ros2=True) as bag:
        for i, t in enumerate(stamps):
            frame = frames.load(i)
            k = frame.color_intrinsics
            rgb = (frame.rgb * 255).round().astype(np.uint8)
            depth = (frame.depth * 1000).round().astype(np.uint16)
            bag.write("/camera/color/image_raw", t, bag.image(t, "camera_color_optical_frame", rgb, "rgb8"))
            bag.write("/camera/depth/image_rect_raw", t, bag.image(t, "camera_color_optical_frame", depth, "16UC1"))
            bag.write("/camera/color/camera_info", t, bag.camera_info(
                t, "camera_color_optical_frame", k.width, k.height, (k.fx, k.fy, k.cx - 0.5, k.cy - 0.5)))
            bag.write("/odom", t, bag.odometry(t, "odom", "camera_color_optical_frame", frame.c2w))
        if corrected is not None:
            bag.write("/slam/path", stamps[-1], bag.path(stamps[-1], "odom", list(zip(stamps, corrected, strict=True))))
