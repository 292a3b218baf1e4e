"""Failed authentications per client address: logged without flooding the log, refused after too many.

A wrong session token or API key is counted against the address it came from (the port is left
out: a client gets a new one per connection). Once ``limit`` failures fall in ``window`` seconds,
every call from that address that needs a token or key is refused with RESOURCE_EXHAUSTED until
the oldest failure leaves the window; refused calls are not counted, so the address gets ``limit``
guesses per window. The log gets one WARNING per address per ``LOG_INTERVAL`` with the count.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import grpc

from ogserver.errors import ServiceError

log = logging.getLogger(__name__)
LOG_INTERVAL = 10.0
MAX_ADDRESSES = 4096  # past this, addresses with no failure in the window are forgotten


def peer_address(peer: str) -> str:
    """gRPC's peer string (``ipv4:1.2.3.4:5678``, ``ipv6:[::1]:5678``, ``unix:/path``) without the port."""
    kind, _, rest = peer.partition(":")
    if kind in ("ipv4", "ipv6"):
        return rest.rsplit(":", 1)[0].strip("[]")
    return peer


@dataclass
class _Address:
    failures: deque[float] = field(default_factory=deque)
    logged: float = -math.inf
    unlogged: int = 0


class FailedAuthentications:
    def __init__(self, limit: int, window: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.limit = limit
        self.window = window
        self._clock = clock
        self._addresses: dict[str, _Address] = {}
        self._lock = threading.Lock()

    @contextmanager
    def guard(self, address: str) -> Iterator[None]:
        """Refuse an address over its limit; count an UNAUTHENTICATED refusal raised inside."""
        self.check(address)
        try:
            yield
        except ServiceError as refusal:
            if refusal.code == grpc.StatusCode.UNAUTHENTICATED:
                self.record(address, refusal.message)
            raise

    def check(self, address: str) -> None:
        if not self.limit:
            return
        with self._lock:
            entry = self._addresses.get(address)
            if entry is None:
                return
            now = self._clock()
            self._expire(entry, now)
            if len(entry.failures) >= self.limit:
                wait = math.ceil(entry.failures[0] + self.window - now)
                raise ServiceError(
                    grpc.StatusCode.RESOURCE_EXHAUSTED,
                    f"too many failed authentications from {address} ({self.limit} in {self.window:g} s); "
                    f"retry in {max(wait, 1)} s",
                )

    def record(self, address: str, reason: str) -> None:
        with self._lock:
            now = self._clock()
            if len(self._addresses) >= MAX_ADDRESSES:
                self._forget_quiet(now)
            entry = self._addresses.setdefault(address, _Address())
            self._expire(entry, now)
            entry.failures.append(now)
            if now - entry.logged < LOG_INTERVAL:
                entry.unlogged += 1
                return
            count, unlogged = len(entry.failures), entry.unlogged
            entry.logged, entry.unlogged = now, 0
        log.warning("authentication failed from %s: %s (%d failures in the last %g s%s)", address, reason, count,
                    self.window, f", {unlogged} not logged" if unlogged else "")

    def _expire(self, entry: _Address, now: float) -> None:
        while entry.failures and entry.failures[0] <= now - self.window:
            entry.failures.popleft()

    def _forget_quiet(self, now: float) -> None:
        for address in list(self._addresses):
            entry = self._addresses[address]
            self._expire(entry, now)
            if not entry.failures:
                del self._addresses[address]
