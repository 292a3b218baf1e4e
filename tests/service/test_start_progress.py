"""A server's start as the demo and the tests wait for it: the warm-up logged stage by stage, the wait
following that log rather than a fixed deadline, and a time-out that says so with the log's tail."""

from __future__ import annotations

import re
import sys

import pytest
from ogclient import demo
from ogclient.local_server import LocalServer, StartTimeout

from ogmapping.warmup import warm_up

from .scene import TEST_SERVER_CONFIG

# Logs a line every 0.4 s for 2 s, then serves: longer than the 1 s start_timeout below, never that quiet.
SLOW_STARTER = """
import sys, time
for stage in range(5):
    print(f"warm-up: stage {stage}", file=sys.stderr, flush=True)
    time.sleep(0.4)
print("ogserver listening on 127.0.0.1:1 (device cpu)", flush=True)
time.sleep(60)
"""
# Logs one line, then nothing.
STALLED = """
import sys, time
print("warm-up: compiling", file=sys.stderr, flush=True)
time.sleep(60)
"""


def fake_server(tmp_path, script: str, **options) -> LocalServer:
    server = LocalServer(tmp_path / "recordings", log_path=tmp_path / "server.log", **options)
    server.args = [sys.executable, "-c", script]
    return server


def test_the_wait_follows_the_log_past_the_start_timeout(tmp_path) -> None:
    lines: list[str] = []
    with fake_server(tmp_path, SLOW_STARTER, start_timeout=1.0, progress=lines.append) as server:
        assert server.address == "127.0.0.1:1"
    assert lines == [f"warm-up: stage {stage}" for stage in range(5)]


def test_a_quiet_start_times_out_saying_how_long_with_the_log_tail(tmp_path) -> None:
    server = fake_server(tmp_path, STALLED, start_timeout=1.0)
    with pytest.raises(StartTimeout) as raised:
        server.start()
    message = str(raised.value)
    assert re.match(r"ogserver did not start: timed out after \d+ s, the last 1 s without a new line", message)
    assert "(last: warm-up: compiling)" in message and message.endswith("warm-up: compiling\n")
    assert server.process is not None and server.process.poll() is not None  # stopped


def test_the_demo_says_it_timed_out_and_how_to_retry(tmp_path, monkeypatch, capsys) -> None:
    def stalled(record_dir, *args, log_path, start_timeout, progress) -> LocalServer:
        return fake_server(tmp_path, STALLED, start_timeout=start_timeout)

    monkeypatch.setattr(demo, "LocalServer", stalled)
    assert demo.main(["--out", str(tmp_path / "demo"), "--start-timeout", "1", "--quiet"]) == 1
    error = capsys.readouterr().err
    assert "demo failed: ogserver did not start: timed out after" in error
    assert "warm-up: compiling" in error  # the log's tail, not empty
    assert "run `make demo` again" in error and "--start-timeout 2" in error


def test_warm_up_reports_each_stage_as_it_ends() -> None:
    stages: list[tuple[str, float]] = []
    seconds = warm_up("cpu", progress=lambda stage, elapsed: stages.append((stage, elapsed)))
    assert [stage for stage, _ in stages] == ["64x48 frame 1 of 2 mapped", "64x48 frame 2 of 2 mapped",
                                              "64x48 render", "64x48 snapshot"]
    elapsed = [at for _, at in stages]
    assert elapsed == sorted(elapsed) and 0 < elapsed[-1] <= seconds


def test_the_server_logs_its_warm_up_and_the_port_it_bound(tmp_path) -> None:
    lines: list[str] = []
    with LocalServer(tmp_path, "--config", str(TEST_SERVER_CONFIG), "--device", "cpu",
                     progress=lines.append) as server:
        port = server.address.rsplit(":", 1)[1]
    log = "\n".join(lines)
    assert "starting: loading torch and the mapping engine" in log
    assert re.search(r"warm-up: 64x48 snapshot, \d+\.\d s", log)
    assert re.search(r"warmed up on cpu: \d+\.\d s", log)
    assert f"anyone who reaches 127.0.0.1:{port} may" in log and ":0 " not in log
