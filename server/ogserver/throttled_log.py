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
        now = time.monotonic()
        with self._lock:
            if now < self._next:
                self._held += 1
                return
            held, self._held = self._held, 0
            self._next = now + self._interval
        suffix = f" ({held} more since the last such line)" if held else ""
        self._logger.warning("%s%s", message, suffix)
