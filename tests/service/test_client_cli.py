"""The ogclient command line: help everywhere, one clear line when the server is not there or a file is bad."""

from __future__ import annotations

import socket
import subprocess
import sys

import pytest
from mcap.reader import make_reader
from ogapi.v1 import mapping_pb2 as pb
from ogclient.__main__ import main, parser
from ogclient.commands import overrides_from_args
from ogserver import healthcheck
from ogserver.recording.recorder import Recorder

COMMANDS = ["create", "stream", "replay", "repair-recording", "trajectory", "view", "render", "snapshot", "restore",
            "stats", "eval", "list", "correct-poses", "close"]


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


@pytest.mark.parametrize("command", [None, *COMMANDS])
def test_help(command: str | None, capsys: pytest.CaptureFixture) -> None:
    with pytest.raises(SystemExit) as done:
        parser().parse_args([command, "--help"] if command else ["--help"])
    assert done.value.code == 0
    assert "usage: ogclient" in capsys.readouterr().out


def test_unreachable_server_is_one_line_and_non_zero(capsys: pytest.CaptureFixture) -> None:
    code = main(["--server", f"127.0.0.1:{free_port()}", "--timeout", "0.5", "list"])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert err.count("\n") == 0 and "cannot reach an ogserver" in err


def test_config_overrides_are_resolved_locally_then_sent_as_text(tmp_path) -> None:
    """A bad key or value fails before any call, with the message the server's resolve would give."""
    with pytest.raises(ValueError, match=r"config keyframes\.iterations expects int, got 'many'"):
        overrides_from_args(parser().parse_args(["create", "--set", "keyframes.iterations=many"]))
    config_file = tmp_path / "config.yaml"
    config_file.write_text("keyframes:\n  iterations: 4\n  local_count: 2\n")
    args = parser().parse_args(["create", "--config", str(config_file), "--set", "keyframes.local_count=3"])
    assert overrides_from_args(args) == {"keyframes.iterations": "4", "keyframes.local_count": "3"}


def test_console_entry_point_exit_code() -> None:
    done = subprocess.run([sys.executable, "-m", "ogclient", "--server", f"127.0.0.1:{free_port()}",
                           "--timeout", "0.5", "stats", "--session", "missing.json"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode != 0 and done.stderr.startswith("ogclient: ")


def test_server_rejects_bad_flags() -> None:
    done = subprocess.run([sys.executable, "-m", "ogserver", "--max-sessions", "0"],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "limits.max_sessions" in done.stderr


def test_healthcheck_says_no_when_nothing_listens() -> None:
    assert not healthcheck.check(f"127.0.0.1:{free_port()}", timeout=0.5)


def test_repair_recording_needs_no_server(tmp_path, capsys: pytest.CaptureFixture) -> None:
    path, cut, repaired = tmp_path / "session.mcap", tmp_path / "cut.mcap", tmp_path / "repaired.mcap"
    recorder = Recorder(path, pb.SessionConfig(session_id="0" * 32, preset="sparse"))
    cut.write_bytes(path.read_bytes()[:-20])  # the session config, then a crash while writing the next frame
    recorder.close()
    unreachable = ["--server", f"127.0.0.1:{free_port()}", "--timeout", "0.5"]
    assert main([*unreachable, "repair-recording", str(cut), str(repaired)]) == 0
    assert "1 messages" in capsys.readouterr().out
    with open(repaired, "rb") as stream:
        assert make_reader(stream).get_summary().statistics.message_count == 1
    cut.write_bytes(b"not an mcap file at all")
    assert main([*unreachable, "repair-recording", str(cut), str(tmp_path / "again.mcap")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "not a readable recording" in err


@pytest.mark.parametrize(("name", "data", "problem"), [
    ("room.safetensors", b"not a snapshot", "snapshot"),
    ("room.mcap", b"not an mcap file at all", "not a readable recording"),
    ("missing.safetensors", None, "missing.safetensors: no such file"),
])
def test_view_of_a_map_it_cannot_read_is_one_line_and_exit_2(tmp_path, name: str, data: bytes | None,
                                                             problem: str) -> None:
    path = tmp_path / name
    if data is not None:
        path.write_bytes(data)
    done = subprocess.run([sys.executable, "-m", "ogclient", "view", str(path), "--device", "cpu"],
                          capture_output=True, text=True, timeout=120)
    assert (done.returncode, done.stdout) == (2, "")
    assert done.stderr.startswith("ogclient: ") and done.stderr.count("\n") == 1 and problem in done.stderr
