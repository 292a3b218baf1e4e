"""Server settings: file then flags, unknown names and bad limits refused."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from ogserver.settings import load

from ogmapping.config import ConfigBounds

from .scene import TEST_SERVER_CONFIG


def test_defaults_then_file_then_flags(tmp_path: Path) -> None:
    path = tmp_path / "server.json"
    path.write_text(json.dumps({"device": "cpu", "limits": {"max_sessions": 2, "queue_depth": 3}}))
    settings = load(path, {"max_sessions": 5, "record_dir": "elsewhere", "device": None})
    assert settings.device == "cpu"
    assert settings.limits.max_sessions == 5 and settings.limits.queue_depth == 3
    assert settings.record_dir == "elsewhere"
    assert settings.limits.max_anchors == 0


def test_live_view_flags() -> None:
    settings = load(None, {"foxglove_port": 0, "view_seconds": 0.5, "record_views": False, "realtime_queue_depth": 2})
    assert settings.live.foxglove and settings.live.view_seconds == 0.5 and not settings.live.record_views
    assert settings.limits.realtime_queue_depth == 2
    assert not load().live.foxglove


def test_worker_processes_go_with_both_live_views() -> None:
    settings = load(None, {"workers": 2, "foxglove_port": 0, "web_port": 0})
    assert settings.workers == 2 and settings.live.foxglove and settings.live.web_port == 0


def test_skipped_recording_flags_reach_the_limits() -> None:
    from ogserver.__main__ import parser

    args = parser().parse_args(["--max-skipped-recording-bytes", "5", "--skipped-recording-bytes-per-second", "0"])
    flags = {key: value for key, value in vars(args).items() if key not in ("config", "log_level")}
    limits = load(None, flags).limits
    assert limits.max_skipped_recording_bytes == 5 and limits.skipped_recording_bytes_per_second == 0


def test_the_test_server_config_loads() -> None:
    assert load(TEST_SERVER_CONFIG).limits.max_image_pixels == 65536


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("colour: blue\n", "unknown settings key 'colour'"),
        ("limits:\n  max_sesions: 2\n", "unknown settings key 'limits.max_sesions'"),
        ("limits:\n  max_sessions: 0\n", "limits.max_sessions"),
        ("limits:\n  queue_depth: two\n", "limits.queue_depth expects int"),
        ("limits: 3\n", "settings limits expects a mapping"),
        ("address: nowhere\n", "HOST:PORT"),
        ("- 1\n", "must hold a mapping"),
        ("config_bounds:\n  max_iterations: 0\n", "config_bounds.max_iterations is out of range: must be >= 1, got 0"),
        ("config_bounds:\n  max_iteration: 10\n", "unknown settings key 'config_bounds.max_iteration'"),
        ("frame_seconds: -1\n", "frame_seconds is out of range: must be >= 0 and finite, got -1.0"),
        ("grace_seconds: .inf\n", "grace_seconds is out of range: must be >= 0 and finite, got inf"),
        ("checkpoint_interval: -1\n", "checkpoint_interval is out of range: must be >= 0, got -1"),
        ("checkpoint_interval: 2.5\n", "checkpoint_interval expects int"),
        ("resume: 1\n", "resume expects bool"),
        ("limits:\n  realtime_queue_depth: 0\n", "limits.realtime_queue_depth is out of range: must be >= 1, got 0"),
        ("live:\n  foxglove_port: -2\n", r"live.foxglove_port is out of range: must be in \[-1, 65535\], got -2"),
        ("live:\n  foxglove_port: 0\n  view_seconds: 0\n", "live.foxglove_port needs live.view_seconds > 0"),
        ("live:\n  view_points: 0\n", "live.view_points is out of range: must be >= 1, got 0"),
        ("workers: -1\n", "workers is out of range: must be >= 0, got -1"),
        ("workers: 2\ncluster: auto\n", "workers and cluster do not go together"),
    ],
)
def test_bad_settings_are_refused(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "server.yaml"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        load(path)


def test_an_operator_tightens_config_bounds_and_the_frame_budget(tmp_path: Path) -> None:
    path = tmp_path / "server.yaml"
    path.write_text("config_bounds:\n  max_iterations: 20\n  min_voxel_size: 0.05\nframe_seconds: 10\n")
    settings = load(path, {"frame_seconds": 5.0})
    assert settings.config_bounds.max_iterations == 20 and settings.config_bounds.min_voxel_size == 0.05
    assert settings.config_bounds.max_n_offsets == ConfigBounds().max_n_offsets, "the other bounds keep their defaults"
    assert settings.frame_seconds == 5.0
