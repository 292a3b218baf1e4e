"""The ogclient command line: help everywhere, one clear line when the server is not there."""

from __future__ import annotations

import socket
import subprocess
import sys

import pytest
from ogclient.__main__ import main, parser
from ogserver import healthcheck

COMMANDS = ["create", "stream", "replay", "render", "snapshot", "restore", "stats", "eval", "list", "close"]


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
