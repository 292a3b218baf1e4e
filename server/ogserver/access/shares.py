"""How much of something each key holds at once, at most ``limit`` each: a caller's call slots, a
session's snapshot calls, a client address's connections."""

from __future__ import annotations

import threading
from collections import Counter


class Shares:
    """Counts per key, each held to ``limit`` (0: no limit); keys holding nothing are forgotten."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self._held: Counter[str] = Counter()
        self._lock = threading.Lock()

    def take(self, key: str) -> bool:
        """One more for ``key``, or False (nothing taken) where it holds its limit."""
        with self._lock:
            if self.limit and self._held[key] >= self.limit:
                return False
            self._held[key] += 1
            return True

    def give_back(self, key: str) -> None:
        with self._lock:
            self._held[key] -= 1
            if not self._held[key]:
                del self._held[key]
