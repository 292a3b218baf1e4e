"""``--bag`` and its flags on ``ogmap run`` and ``ogclient stream/eval``: parsed into the reader's options,
refused where they do not go with the dataset, listed in --help."""

from __future__ import annotations

from pathlib import Path

import pytest

pytest.importorskip("rosbags")

from ogclient.__main__ import parser as client_parser
from rosbag_writer import BagRecorder
from test_rosbag_reader import N, stamp, write_frames

from ogmapping.cli import commands
from ogmapping.cli.options import dataset_source, open_frame_set
from ogmapping.datasets import open_dataset
from ogmapping.datasets.synthetic import SyntheticSource


@pytest.fixture
def bag(tmp_path: Path) -> Path:
    frames = list(SyntheticSource(n_frames=N, width=48, height=36))
    path = tmp_path / "robot.bag"
    with BagRecorder(path, ros2=False) as recorder:
        for i in range(N):
            write_frames(recorder, frames, i, "rgb8", "16UC1")
            recorder.write("/pose", stamp(i), recorder.pose_stamped(stamp(i), "map", frames[i].c2w))
    return path


def test_bag_flags_become_reader_options(bag: Path) -> None:
    args = commands.parser().parse_args(["run", "--bag", str(bag), "--color-topic", "/camera/color/image_raw",
                                         "--pose-topic", "/pose", "--pair-tolerance", "0.005", "--camera-frame", "cam"])
    assert dataset_source(args) == (str(bag), "bag", {"color_topic": "/camera/color/image_raw", "pose_topic": "/pose",
                                                      "camera_frame": "cam", "pair_tolerance": 0.005})
    # --data finds a bag by its name too, and takes the same flags.
    args = client_parser().parse_args(["stream", "--data", str(bag), "--pose-tolerance", "0.1", "--frames", "0:3"])
    assert dataset_source(args) == (str(bag), "bag", {"pose_tolerance": 0.1})
    frame_set = open_frame_set(args)
    assert frame_set.selection.streamed == [0, 1, 2] and len(frame_set.source) == N


def test_bag_flags_are_refused_elsewhere(bag: Path) -> None:
    args = commands.parser().parse_args(["run", "--data", "synthetic", "--color-topic", "/camera/color/image_raw"])
    with pytest.raises(ValueError, match="--color-topic is for ROS bags; synthetic is not one"):
        dataset_source(args)
    with pytest.raises(ValueError, match="--format tum does not go with it"):
        dataset_source(commands.parser().parse_args(["run", "--bag", str(bag), "--format", "tum"]))
    with pytest.raises(SystemExit):
        commands.parser().parse_args(["run", "--bag", str(bag), "--data", "synthetic"])


def test_ogmap_run_passes_the_bag_to_the_runner(bag: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import ogmapping.cli.runner

    seen = {}

    def run(options, config):
        seen["options"] = options
        return {key: None for key in ("streamed", "heldout", "processing_fps", "snapshot_bytes", "anchors",
                                      "gaussians", "device", "resolution")}

    monkeypatch.setattr(ogmapping.cli.runner, "run", run)
    assert commands.main(["run", "--bag", str(bag), "--fixed-frame", "map", "--pose-topic", "/pose", "--quiet"]) == 0
    options = seen["options"]
    assert (options.data, options.format) == (str(bag), "bag")
    assert options.dataset_options == {"fixed_frame": "map", "pose_topic": "/pose"}


def test_render_takes_a_frame_of_a_bag(bag: Path) -> None:
    args = client_parser().parse_args(["render", "--session", "s.json", "--bag", str(bag), "--position", "2",
                                       "--pose-topic", "/pose"])
    data, format, options = dataset_source(args)
    assert (data, format, options) == (str(bag), "bag", {"pose_topic": "/pose"})
    assert open_dataset(data, format, **options)[2].timestamp == pytest.approx(stamp(2) * 1e-9, abs=1e-6)


@pytest.mark.parametrize("command", [["run"], ["stream"], ["eval", "--session", "s.json"], ["render"]])
def test_help_lists_the_bag_flags(command: list[str], capsys: pytest.CaptureFixture) -> None:
    parser = commands.parser() if command == ["run"] else client_parser()
    with pytest.raises(SystemExit):
        parser.parse_args([command[0], "--help"])
    text = capsys.readouterr().out
    for flag in ("--bag PATH", "--color-topic", "--depth-topic", "--info-topic", "--depth-info-topic", "--pose-topic",
                 "--fixed-frame", "--camera-frame", "--body-frame", "--pair-tolerance", "--pose-tolerance"):
        assert flag in text, flag
    assert "OpenCV's axes" in text
