"""``ogclient stream --bag``: a ROS 2 bag (MCAP) from the synthetic room streamed into a session, its topics,
pose source and frame count reported first."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags")

from ogapi.v1 import mapping_pb2 as pb
from ogclient.__main__ import main as ogclient_main
from ogclient.connection import SessionRef
from rosbag_writer import BagRecorder

from ogmapping.datasets import open_dataset

from .conftest import ServerHandle
from .scene import FROZEN, PRESET

T0 = 1_700_000_000 * 10**9


def write_bag(path: Path, count: int) -> None:
    source = open_dataset("synthetic", "synthetic", n_frames=count, width=80, height=60)
    k = source.intrinsics
    with BagRecorder(path, ros2=True) as bag:
        for i in range(count):
            frame, t = source[i], T0 + i * 33_333_333
            rgb = (frame.rgb * 255).round().astype(np.uint8)
            depth = (frame.depth * 1000).round().astype(np.uint16)
            bag.write("/camera/color/image_raw", t, bag.image(t, "camera_color_optical_frame", rgb, "rgb8"))
            bag.write("/camera/depth/image_rect_raw", t, bag.image(t, "camera_color_optical_frame", depth, "16UC1"))
            bag.write("/camera/color/camera_info", t, bag.camera_info(t, "camera_color_optical_frame", 80, 60,
                                                                      (k.fx, k.fy, k.cx - 0.5, k.cy - 0.5)))
            bag.write("/odom", t, bag.odometry(t, "odom", "camera_color_optical_frame", frame.c2w))


def test_stream_a_bag(server: ServerHandle, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    bag = tmp_path / "robot.mcap"
    write_bag(bag, 6)
    overrides = [flag for key, value in FROZEN.items() for flag in ("--set", f"{key}={value}")]
    session_file = tmp_path / "session.json"
    code = ogclient_main(["--server", server.address, "stream", "--bag", str(bag), "--preset", PRESET, *overrides,
                          "--pair-tolerance", "0.01", "--session-out", str(session_file), "--quiet"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert f"bag:{bag}: poses: /odom (nav_msgs/msg/Odometry), camera_color_optical_frame in odom" in out
    assert "6 frames: 0 colour images without depth within 0.01 s" in out
    session = SessionRef.load(session_file)
    stats = server.stub.GetStats(pb.GetStatsRequest(session_id=session.session_id), metadata=session.metadata())
    assert stats.frames == 5 and stats.frames_rejected == 0  # position 5 is held out, as for any dataset
    server.stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id), metadata=session.metadata())
