"""Failed authentications: counted per client address and across the server, logged without
flooding the log, never held against a valid credential.

The servicer checks the key or token first; only a wrong one reaches ``failed``. It is counted
against the address it came from (the port left out: a client gets a new one per connection) and
against the whole server. Once ``limit`` failures from that address, or ``total_limit`` from all
addresses together, fall within ``window`` seconds, a wrong credential is answered
RESOURCE_EXHAUSTED instead of UNAUTHENTICATED. A right one always passes: clients behind one NAT,
ingress or load balancer share an address, and one of them failing must not lock out the others.

What a guesser learns is what it would learn without this module: whether the credential it
presented is right, decided by the same check in the same time. Keeping that answer from it means
refusing right credentials too, which locks out every honest client sharing the address (or, counted
server-wide, every client); delaying only the wrong answers gives them away by the delay. Guessing
is kept out by the credentials themselves (session tokens and generated keys carry 256 random
bits); this module keeps it visible (the log, the status) and bounded in memory.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import grpc

from ogserver.errors import ServiceError

log = logging.getLogger(__name__)
LOG_INTERVAL = 10.0  # one WARNING per address this often at most
LOG_LINES = 10  # and at most this many WARNINGs per LOG_INTERVAL from all addresses
MAX_ADDRESSES = 4096  # addresses counted at once; past it, the one that failed least recently is forgotten


def peer_address(peer: str) -> str:
    """gRPC's peer string (``ipv4:1.2.3.4:5678``, ``ipv6:[::1]:5678``, ``unix:/path``) without the port."""
    kind, _, rest = peer.partition(":")
    if kind in ("ipv4", "ipv6"):
        return rest.rsplit(":", 1)[0].strip("[]")
    return peer


@dataclass
class Window:
    """Events in the last ``seconds``, estimated from this fixed window's count and the previous one's
    (weighted by the part of it still inside): constant memory, however many events."""

    seconds: float
    start: float
    count: int = 0
    previous: int = 0

    def add(self, now: float) -> None:
        self._roll(now)
        self.count += 1

    def recent(self, now: float) -> float:
        if self.seconds <= 0:
            return 0.0
        self._roll(now)
        return self.previous * (1.0 - (now - self.start) / self.seconds) + self.count

    def _roll(self, now: float) -> None:
        if self.seconds <= 0 or now - self.start < self.seconds:
            return
        periods = math.floor((now - self.start) / self.seconds)
        self.previous = self.count if periods == 1 else 0
        self.count = 0
        self.start += periods * self.seconds


@dataclass
class _Address:
    failures: Window
    logged: float = -math.inf
    unlogged: int = 0  # failures since its last WARNING line


class FailedAuthentications:
    def __init__(self, limit: int, window: float, total_limit: int = 0, clock: Callable[[], float] = time.monotonic,
                 max_addresses: int = MAX_ADDRESSES) -> None:
        self.limit = limit
        self.window = window
        self.total_limit = total_limit
        self.max_addresses = max_addresses
        self._clock = clock
        self._addresses: OrderedDict[str, _Address] = OrderedDict()  # least recently failed first
        self._total = Window(window, clock())
        self._lines: deque[float] = deque(maxlen=LOG_LINES)
        self._lock = threading.Lock()

    def __len__(self) -> int:
        """Addresses counted now (at most ``max_addresses``)."""
        return len(self._addresses)

    @contextmanager
    def guard(self, address: str) -> Iterator[None]:
        """Count an UNAUTHENTICATED refusal raised inside; past a limit it leaves as RESOURCE_EXHAUSTED."""
        try:
            yield
        except ServiceError as refusal:
            if refusal.code != grpc.StatusCode.UNAUTHENTICATED:
                raise
            raise self.failed(address, refusal) from None

    def failed(self, address: str, refusal: ServiceError) -> ServiceError:
        """Count a wrong credential from ``address``; the refusal to answer it with."""
        with self._lock:
            now = self._clock()
            entry = self._entry(address, now)
            answer = self._answer(address, refusal, entry, now)
            entry.failures.add(now)
            self._total.add(now)
            entry.unlogged += 1
            counts = self._counts(entry, now)
        if counts is not None:
            log.warning("authentication failed from %s: %s (%s)", address, answer.message, counts)
        return answer

    def _entry(self, address: str, now: float) -> _Address:
        entry = self._addresses.get(address)
        if entry is None:
            if len(self._addresses) >= self.max_addresses:
                self._addresses.popitem(last=False)
            entry = self._addresses[address] = _Address(Window(self.window, now))
        self._addresses.move_to_end(address)
        return entry

    def _answer(self, address: str, refusal: ServiceError, entry: _Address, now: float) -> ServiceError:
        """UNAUTHENTICATED, or RESOURCE_EXHAUSTED once the address or the server is past its limit."""
        if self.limit and entry.failures.recent(now) >= self.limit:
            where = f"from {address} ({self.limit} in {self.window:g} s)"
        elif self.total_limit and self._total.recent(now) >= self.total_limit:
            where = f"from all addresses ({self.total_limit} in {self.window:g} s)"
        else:
            return refusal
        return ServiceError(grpc.StatusCode.RESOURCE_EXHAUSTED, f"too many failed authentications {where}; "
                                                                f"{refusal.message}")

    def _counts(self, entry: _Address, now: float) -> str | None:
        """The counts a WARNING line gives now, or None when none is written (too soon for the address, or
        ``LOG_LINES`` lines already in the interval: its failures go out with its next line)."""
        if now - entry.logged < LOG_INTERVAL:
            return None
        if len(self._lines) == LOG_LINES and now - self._lines[0] < LOG_INTERVAL:
            return None
        self._lines.append(now)
        since = "" if entry.logged == -math.inf else " since its previous line"
        count, entry.unlogged, entry.logged = entry.unlogged, 0, now
        return (f"{count} from this address{since}; {round(self._total.recent(now))} from all addresses "
                f"in the last {self.window:g} s")
