"""Run an ogserver as a child process on a free local port (the demo and the tests use it)."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

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


class LocalServer:
    """``with LocalServer(record_dir) as server: ... server.address``; stopped with SIGTERM on exit."""

    def __init__(self, record_dir: str | Path, *extra_args: str, log_path: str | Path | None = None,
                 start_timeout: float = 120.0) -> None:
        self.record_dir = Path(record_dir)
        self.args = [sys.executable, "-m", "ogserver", "--address", "127.0.0.1:0",
                     "--record-dir", str(self.record_dir), *extra_args]
        self.log_path = Path(log_path) if log_path else self.record_dir / "server.log"
        self.start_timeout = start_timeout
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
        deadline = time.monotonic() + self.start_timeout
        while not self._ready.wait(0.1):
            if self.process.poll() is not None or time.monotonic() > deadline:
                self.stop()
                tail = self.log_path.read_text()[-2000:]
                raise RuntimeError(f"ogserver did not start (exit {self.process.returncode}); log tail:\n{tail}")
        return self

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
