"""``ogclient view``: the web view of one map on this machine, served by the server's own entry for it,
``python -m ogserver view MAP``, run as a child process (the client never imports the server).

The child prints its progress, then ``ogserver map view on URL``; a map it cannot read is its one line
``ogserver view: ...`` on stderr and exit status 2, reported here as this command's one line (exit
status 2 too). The command stops the child whenever it ends itself: Ctrl-C, SIGTERM or an error
(SIGTERM, then SIGKILL ``STOP_SECONDS`` later).
"""

from __future__ import annotations

import io
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO

from ogclient.connection import ClientError
from ogclient.local_server import stop_child

READY_PREFIX = "ogserver map view on"
ERROR_PREFIX = "ogserver view:"
STOP_SECONDS = 3.0


class Stderr(threading.Thread):
    """Passes the child's stderr through as it comes, a progress bar's redrawn line (ended by a carriage
    return) too, keeping its error line (``ogserver view: ...``) to report as ours."""

    def __init__(self, stream: IO[str]) -> None:
        super().__init__(name="ogserver-view-stderr", daemon=True)
        self.stream = stream
        self.error = ""

    def run(self) -> None:
        for segment in segments(self.stream):
            if segment.startswith(ERROR_PREFIX):
                self.error = segment[len(ERROR_PREFIX):].strip()
            else:
                sys.stderr.write(segment)
                sys.stderr.flush()


def segments(stream: IO[str]) -> Iterator[str]:
    """``stream``'s text in pieces that each end at a newline or a carriage return (the last at its end)."""
    piece = ""
    while character := stream.read(1):
        piece += character
        if character in "\r\n":
            yield piece
            piece = ""
    if piece:
        yield piece


def view(path: Path, port: int, device: str, ready: Callable[[str], None], quiet: bool = False) -> int:
    """Serve the map at ``path`` until Ctrl-C or SIGTERM, calling ``ready(url)`` once its page is served; the
    child's progress lines and bar (none when ``quiet``) are shown as they come. ClientError where it fails."""
    command = [sys.executable, "-m", "ogserver", "view", str(path), "--port", str(port), "--device", device,
               *(["--quiet"] if quiet else [])]
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)  # stops the child too, like Ctrl-C
    child = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    stderr = Stderr(io.TextIOWrapper(child.stderr, newline=""))  # carriage returns kept: a bar redraws its line
    stderr.start()
    try:
        for line in io.TextIOWrapper(child.stdout):
            if line.startswith(READY_PREFIX):
                ready(line[len(READY_PREFIX):].strip())
            else:
                print(line, end="", flush=True)
    except KeyboardInterrupt:
        return 0
    finally:
        status = stop_child(child, STOP_SECONDS)
        signal.signal(signal.SIGTERM, previous)
    stderr.join()
    if status == 0:  # ended by a signal to the whole process group: Ctrl-C in a terminal
        return 0
    raise ClientError(stderr.error or f"ogserver view exited with status {status}")
