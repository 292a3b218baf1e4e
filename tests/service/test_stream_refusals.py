"""``ogclient stream`` with a frame the client itself refuses (a bag image larger than its CameraInfo):
the frames before it stay in the session and the command ends with one line naming the problem,
not grpc's `UNKNOWN: Exception iterating requests!`."""

from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip("rosbags")

from ogclient.__main__ import main
from rosbag_writer import BagRecorder, compressed_depth_16, encode_png
from test_rosbag_hostile import FRAME, png_header_only
from test_rosbag_reader import depth_mm, published_k, rgb8, stamp

from ogmapping.datasets.synthetic import SyntheticSource

from .inprocess import serving, settings

HUGE = 20000


def write_bag(path: Path, bomb_at: int, count: int = 3) -> Path:
    """Compressed frames of the synthetic room; frame ``bomb_at``'s colour PNG claims 20000x20000."""
    frames = list(SyntheticSource(n_frames=count, width=48, height=36))
    with BagRecorder(path, ros2=True) as bag:
        for i, frame in enumerate(frames):
            t = stamp(i)
            colour = png_header_only(HUGE, HUGE) if i == bomb_at else encode_png(rgb8(frame)[:, :, ::-1])
            bag.write("/cam/color/image_raw/compressed", t, bag.compressed(t, FRAME, colour, "rgb8; png compressed"))
            bag.write("/cam/color/camera_info", t, bag.camera_info(t, FRAME, 48, 36, published_k(frame)))
            bag.write("/cam/depth/image_raw/compressedDepth", t, bag.compressed(
                t, FRAME, compressed_depth_16(depth_mm(frame)), "16UC1; compressedDepth png"))
            bag.write("/pose", t, bag.pose_stamped(t, "map", frame.c2w))
    return path


def test_a_refused_bag_frame_ends_the_stream_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    bag = write_bag(tmp_path / "bomb.mcap", bomb_at=1)
    with serving(settings(tmp_path)) as running:
        code = main(["--server", running.address, "stream", "--bag", str(bag), "--pose-topic", "/pose", "--quiet",
                     "--session-out", str(tmp_path / "session.json")])
        listed = main(["--server", running.address, "list"])
    captured = capsys.readouterr()
    assert code == 2 and listed == 0
    assert captured.err.count("\n") == 1
    assert captured.err.startswith(f"ogclient: {bag}: /cam/color/image_raw/compressed at {stamp(1)} ns: image is "
                                   f"{HUGE}x{HUGE} but its CameraInfo says 48x36")
    assert "frames=1 " in captured.out  # the frame before the refused one was mapped
