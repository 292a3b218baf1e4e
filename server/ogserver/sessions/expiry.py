"""Closes sessions nobody uses (``session_idle_seconds``), so idle ones do not hold the session limit."""

from __future__ import annotations

import threading

from ogserver.sessions.hosting import SessionHost

CHECKS_PER_LIMIT = 10  # a session is closed at most a tenth of the limit late
LONGEST_CHECK_INTERVAL = 10.0


class Expiry:
    def __init__(self, registry: SessionHost) -> None:
        self._registry = registry
        self._stopped = threading.Event()
        limit = registry.settings.access.session_idle_seconds
        self._interval = min(limit / CHECKS_PER_LIMIT, LONGEST_CHECK_INTERVAL)
        self._thread = threading.Thread(target=self._run, name="expiry", daemon=True) if limit else None

    def start(self) -> Expiry:
        if self._thread is not None:
            self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stopped.wait(self._interval):
            self._registry.expire_idle()

    def stop(self) -> None:
        """No further checks; a close in progress finishes on its own (shutdown closes the others)."""
        self._stopped.set()
