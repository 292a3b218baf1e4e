"""A log line that one client can repeat at will, written at most once per interval.

Lines held back are counted, and the count goes out with the next line written, so the log
still says how often it happened without one client filling the disk.
"""

from __future__ import annotations

import logging
import threading
import time


class ThrottledLog:
    def __init__(self, logger: logging.Logger, interval_seconds: float) -> None:
        self._logger = logger
        self._interval = interval_seconds
        self._lock = threading.Lock()
        self._next = 0.0
        self._held = 0

    def warning(self, message: str) -> None:
        self.log(logging.WARNING, message)

    def log(self, level: int, message: str) -> None:
        now = time.monotonic()
        with self._lock:
            if now < self._next:
                self._held += 1
                return
            held, self._held = self._held, 0
            self._next = now + self._interval
        suffix = f" ({held} more since the last such line)" if held else ""
        self._logger.log(level, "%s%s", message, suffix)


class ThrottledHandler(logging.Handler):
    """Passes a library's records on to ``target``, at most one per interval for each logger name and level.

    Installed on a library's logger that does not propagate, it stands between code the server does
    not control (which may log a line per message a client sends) and the server's log.
    """

    def __init__(self, target: logging.Logger, interval_seconds: float) -> None:
        super().__init__()
        self._target = target
        self._interval = interval_seconds
        self._lines: dict[tuple[str, int], ThrottledLog] = {}
        self._lines_lock = threading.Lock()

    def emit(self, record: logging.LogRecord) -> None:
        key = (record.name, record.levelno)
        with self._lines_lock:
            line = self._lines.setdefault(key, ThrottledLog(self._target, self._interval))
        line.log(record.levelno, f"{record.name}: {record.getMessage()}")


def throttle_library(name: str, target: logging.Logger, interval_seconds: float) -> None:
    """Route the ``name`` logger and its children through a ``ThrottledHandler`` (once per process)."""
    library = logging.getLogger(name)
    if any(isinstance(handler, ThrottledHandler) for handler in library.handlers):
        return
    library.addHandler(ThrottledHandler(target, interval_seconds))
    library.propagate = False
