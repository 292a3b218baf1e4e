"""A client stream that must keep moving: each message within an idle timeout, all within a total one.

gRPC's request iterator blocks until the client sends, so a client that sends nothing would hold
the call's thread (and whatever the call reserved) for ever. ``Paced`` reads the iterator in a
helper thread, one message at a time and only when asked, so backpressure still reaches the
client; a wait past either limit raises DEADLINE_EXCEEDED in the caller. The helper starts
with the first read and ends at the end of the stream or at ``close()``, which a caller that
stops reading early must call.
"""

from __future__ import annotations

import math
import queue
import threading
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Generic, TypeVar

import grpc

from ogserver.errors import ServiceError

T = TypeVar("T")


@dataclass(frozen=True)
class Timeout:
    seconds: float  # 0: no limit
    setting: str  # the server setting that sets it, named in the refusal


NO_TIMEOUT = Timeout(0.0, "")


@dataclass(frozen=True)
class _End:
    failure: BaseException | None = None


class Paced(Generic[T]):
    """Iterate ``requests``, each message within ``idle`` of asking for it, all within ``total``."""

    def __init__(self, requests: Iterable[T], idle: Timeout, total: Timeout = NO_TIMEOUT) -> None:
        self._idle = idle
        self._total = total
        self._deadline = time.monotonic() + total.seconds if total.seconds else math.inf
        self._asks: queue.SimpleQueue[bool] = queue.SimpleQueue()
        self._items: queue.SimpleQueue[T | _End] = queue.SimpleQueue()
        self._ended = False
        self._helper = threading.Thread(target=self._pump, args=(requests,), name="paced", daemon=True)

    def _pump(self, requests: Iterable[T]) -> None:
        source = iter(requests)
        while self._asks.get():
            try:
                self._items.put(next(source))
            except StopIteration:
                self._items.put(_End())
                return
            except Exception as failure:  # a cancelled call ends its iterator with an error
                self._items.put(_End(failure))
                return

    def __iter__(self) -> Iterator[T]:
        return self

    def __next__(self) -> T:
        if self._ended:
            raise StopIteration
        if self._helper.ident is None:
            self._helper.start()  # on first use: a call refused before reading leaves no thread behind
        self._asks.put(True)
        idle = self._idle.seconds or math.inf
        wait = min(idle, self._deadline - time.monotonic())
        try:
            item = self._items.get(timeout=max(wait, 0.0) if math.isfinite(wait) else None)
        except queue.Empty:
            self.close()
            raise self._timeout(over_total=wait < idle) from None
        if isinstance(item, _End):
            self._ended = True
            if item.failure is not None:
                raise item.failure
            raise StopIteration
        return item

    def close(self) -> None:
        """Read no more: the helper ends now, or once a read in progress returns (when the call ends)."""
        self._ended = True
        self._asks.put(False)

    def _timeout(self, over_total: bool) -> ServiceError:
        if over_total:
            reason = f"the call did not finish within {self._total.seconds:g} s (the server's {self._total.setting})"
        else:
            reason = f"the client sent nothing for {self._idle.seconds:g} s (the server's {self._idle.setting})"
        return ServiceError(grpc.StatusCode.DEADLINE_EXCEEDED, reason)
