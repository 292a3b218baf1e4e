"""What bounds a web view connection beyond the count of them: a deadline for each request's head, and a
share of the connections per client address.

A timeout per read does not bound a request: a client sending one header byte every few seconds keeps
its connection, and 64 such connections took the web view from everyone. Here the TLS handshake, the
request line and the headers of each request must arrive within ``HEAD_SECONDS`` in all, or the
connection is shut; a kept-alive connection gets the same deadline for its next request. And one
address holds at most ``PER_ADDRESS`` connections at once, so a single client cannot take them all.
"""

from __future__ import annotations

import contextlib
import socket
import threading
from collections import Counter

HEAD_SECONDS = 10.0
PER_ADDRESS = 16


class HeadDeadline:
    """Shuts ``connection`` unless ``met`` is called within ``seconds`` of ``arm``."""

    def __init__(self, connection: socket.socket, seconds: float = HEAD_SECONDS) -> None:
        self._connection = connection
        self._seconds = seconds
        self._timer: threading.Timer | None = None

    def arm(self) -> None:
        self.met()
        self._timer = threading.Timer(self._seconds, self._expire)
        self._timer.daemon = True
        self._timer.start()

    def met(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _expire(self) -> None:
        with contextlib.suppress(OSError):  # a connection already gone
            self._connection.shutdown(socket.SHUT_RDWR)  # the handler's blocked read returns at once


class AddressShares:
    """Connections open per client address, at most ``limit`` each."""

    def __init__(self, limit: int = PER_ADDRESS) -> None:
        self.limit = limit
        self._open: Counter[str] = Counter()
        self._lock = threading.Lock()

    def take(self, address: str) -> bool:
        with self._lock:
            if self._open[address] >= self.limit:
                return False
            self._open[address] += 1
            return True

    def give_back(self, address: str) -> None:
        with self._lock:
            self._open[address] -= 1
            if not self._open[address]:
                del self._open[address]
