"""How much of a realtime session's skipped frames its recording takes: a total and a rate per session.

A realtime sensor can send far faster than the session maps, and every skipped frame would otherwise
reach the disk at network speed. Mapped frames are always recorded (a replay needs them); skipped
ones only while the session's budget (``limits.max_skipped_recording_bytes``) and its rate (a token
bucket holding one second of ``limits.skipped_recording_bytes_per_second``) cover them.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable


class SkippedBudget:
    """Bytes a session's recording may still take for skipped frames; thread-safe."""

    def __init__(self, total: int, per_second: int, clock: Callable[[], float] = time.monotonic) -> None:
        self._left = total
        self._rate = per_second
        self._clock = clock
        self._tokens = float(per_second)  # a full second's worth to start with
        self._filled = clock()
        self._lock = threading.Lock()

    def take(self, size: int) -> bool:
        """Whether a skipped frame of ``size`` bytes is recorded; if so, its bytes are spent."""
        with self._lock:
            now = self._clock()
            self._tokens = min(float(self._rate), self._tokens + (now - self._filled) * self._rate)
            self._filled = now
            if size > self._left or size > self._tokens:
                return False
            self._left -= size
            self._tokens -= size
            return True
