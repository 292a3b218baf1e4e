"""Run an ogserver as a child process on a free local port (the demo and the tests use it)."""

from __future__ import annotations

import io
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

READY_PREFIX = "ogserver listening on"
WEB_PREFIX = "ogserver web view on"


def stop_child(process: subprocess.Popen, timeout: float) -> int:
    """SIGTERM, then SIGKILL where ``process`` is still there ``timeout`` seconds later; its exit status."""
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
        try:
            return process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
    return process.wait()


class StartTimeout(RuntimeError):
    """The server wrote nothing new to its log for ``quiet`` seconds before it served."""

    def __init__(self, waited: float, quiet: float, last_line: str, tail: str) -> None:
        self.waited, self.quiet = waited, quiet
        super().__init__(f"ogserver did not start: timed out after {waited:.0f} s, the last {quiet:.0f} s without "
                         f"a new line in its log (last: {last_line or 'none'}); log tail:\n{tail}")


class LocalServer:
    """``with LocalServer(record_dir) as server: ... server.address``; stopped with SIGTERM on exit.

    The start waits as long as the server makes progress (a first start compiles the kernels, minutes on
    a busy machine, and logs each warm-up stage): it gives up ``start_timeout`` seconds after the log's
    last new line, not that long after the start."""

    def __init__(self, record_dir: str | Path, *extra_args: str, log_path: str | Path | None = None,
                 start_timeout: float = 300.0, progress: Callable[[str], None] | None = None) -> None:
        self.record_dir = Path(record_dir)
        self.args = [sys.executable, "-m", "ogserver", "--address", "127.0.0.1:0",
                     "--record-dir", str(self.record_dir), *extra_args]
        self.log_path = Path(log_path) if log_path else self.record_dir / "server.log"
        self.start_timeout = start_timeout
        self.progress = progress  # hears each line the server logs while it starts
        self.address = ""
        self.ready_line = ""
        self.web_url = ""  # with --web-port: the web view's http(s)://HOST:PORT/
        self.output: list[str] = []
        self.process: subprocess.Popen | None = None
        self._ready = threading.Event()

    def start(self) -> LocalServer:
        self.record_dir.mkdir(parents=True, exist_ok=True)
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        log = open(self.log_path, "w")  # noqa: SIM115 - the child writes to it until it exits
        self.process = subprocess.Popen(self.args, stdout=subprocess.PIPE, stderr=log, text=True, bufsize=1)
        log.close()
        threading.Thread(target=self._follow, daemon=True).start()
        started = last_progress = time.monotonic()
        with open(self.log_path, "rb") as log_lines:
            while not self._ready.wait(0.1):
                now = time.monotonic()
                if self._read_progress(log_lines):
                    last_progress = now
                self._check_started(now - started, now - last_progress)
            self._read_progress(log_lines)
        return self

    def _read_progress(self, log_lines: BinaryIO) -> bool:
        """Whether the log has grown; passes its new complete lines to ``progress``."""
        new = False
        while line := log_lines.readline():
            new = True
            if not line.endswith(b"\n"):  # the rest is still being written: read it again next time
                log_lines.seek(-len(line), io.SEEK_CUR)
                break
            if self.progress is not None:
                self.progress(line.decode(errors="replace").rstrip("\n"))
        return new

    def _check_started(self, waited: float, quiet: float) -> None:
        """RuntimeError where the server exited, StartTimeout (the server stopped) where it has been quiet
        longer than ``start_timeout``."""
        assert self.process is not None
        if self.process.poll() is not None:
            raise RuntimeError(f"ogserver did not start (exit {self.process.returncode}); log tail:\n{self._tail()}")
        if quiet > self.start_timeout:
            tail = self._tail()
            self.stop()
            raise StartTimeout(waited, quiet, tail.strip().splitlines()[-1], tail)

    def _tail(self, characters: int = 2000) -> str:
        """The end of the server's log, or what it printed when the log is empty."""
        tail = self.log_path.read_text()[-characters:]
        return tail if tail.strip() else "(the log is empty; its output: " + ("\n".join(self.output) or "none") + ")"

    def _follow(self) -> None:
        assert self.process is not None and self.process.stdout is not None
        for line in self.process.stdout:
            self.output.append(line.rstrip("\n"))
            if line.startswith(WEB_PREFIX):
                self.web_url = line[len(WEB_PREFIX):].strip()
            if line.startswith(READY_PREFIX):
                self.address = line[len(READY_PREFIX):].split()[0]
                self.ready_line = line.strip()
                self._ready.set()

    def stop(self, timeout: float = 60.0) -> int | None:
        """SIGTERM (the graceful path: recordings closed), SIGKILL if it does not exit in time."""
        return None if self.process is None else stop_child(self.process, timeout)

    def kill(self) -> None:
        """SIGKILL, as a crash would."""
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait()

    def __enter__(self) -> LocalServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
