"""A mapper's time per stage, measured without making the host wait for the device.

On the CPU a stage's time is the host's: ``time.perf_counter`` around it. On CUDA the host only
launches kernels, so its clock around a stage measures launches, and waiting for the device at
each stage's end (13 stages per step) would stall the pipeline the timer is meant to measure.
There each stage records a pair of timing events on the current stream (the mapper's) and goes
on; a pair is read once its end event has completed, which is checked without blocking at each
new stage's start, and every pair still pending is waited for only when the totals are read.

What a CUDA figure means: device time between the stage's start and end on the mapper's stream,
which includes the gaps where the device waited for the host to launch the stage's next kernel.
"""

from __future__ import annotations

import threading
import time
from collections import defaultdict, deque
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Protocol

import torch

# Pairs recorded but not yet read, at most: a step has about 20 timed stages, and the device runs
# a few steps behind the host at most, so reading the oldest pair by waiting (one host
# synchronisation) happens only when something else has stalled the device for long.
MAX_PENDING = 256


class TimingEvent(Protocol):
    """What the timer needs of ``torch.cuda.Event(enable_timing=True)``."""

    def record(self) -> None: ...  # on the current stream

    def query(self) -> bool: ...  # completed? never blocks

    def synchronize(self) -> None: ...  # block until completed

    def elapsed_time(self, end: TimingEvent) -> float: ...  # milliseconds from this event to ``end``


def cuda_event() -> TimingEvent:
    return torch.cuda.Event(enable_timing=True)


@dataclass
class _Pair:
    stage: str
    start: TimingEvent
    end: TimingEvent


class StageTimer:
    """Seconds per stage name, summed over every timing of it.

    ``events`` makes the timing events of the device path (``cuda_event``); None times on the host
    with ``clock``. Thread-safe: stages may be timed from several threads while totals are read.
    """

    def __init__(self, events: Callable[[], TimingEvent] | None = None, max_pending: int = MAX_PENDING,
                 clock: Callable[[], float] = time.perf_counter) -> None:
        self._events = events
        self._max_pending = max_pending
        self._clock = clock
        self._totals: dict[str, float] = defaultdict(float)
        self._pending: deque[_Pair] = deque()
        self._pool: list[TimingEvent] = []
        self._lock = threading.Lock()

    @classmethod
    def for_device(cls, device: torch.device) -> StageTimer:
        """Events on CUDA, the host's clock elsewhere."""
        return cls(cuda_event if device.type == "cuda" else None)

    @property
    def pending(self) -> int:
        """Pairs recorded and not yet read."""
        return len(self._pending)

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Time the block as stage ``name`` (a block that raises is not counted)."""
        if self._events is None:
            start = self._clock()
            yield
            elapsed = self._clock() - start
            with self._lock:
                self._totals[name] += elapsed
            return
        begin = self._begin()
        try:
            yield
        except BaseException:
            with self._lock:
                self._pool.append(begin)
            raise
        with self._lock:
            end = self._event()
            end.record()
            self._pending.append(_Pair(name, begin, end))
            while len(self._pending) > self._max_pending:
                self._read(self._pending.popleft(), wait=True)

    def add(self, name: str, seconds: float) -> None:
        """Count ``seconds`` the host measured itself (work done on another thread) to stage ``name``."""
        with self._lock:
            self._totals[name] += seconds

    def totals(self) -> dict[str, float]:
        """Seconds per stage so far; on the device path this waits for every pair still pending."""
        with self._lock:
            while self._pending:
                self._read(self._pending.popleft(), wait=True)
            return dict(self._totals)

    def _begin(self) -> TimingEvent:
        with self._lock:
            while self._pending and self._pending[0].end.query():
                self._read(self._pending.popleft(), wait=False)
            event = self._event()
            event.record()
            return event

    def _event(self) -> TimingEvent:
        assert self._events is not None
        return self._pool.pop() if self._pool else self._events()

    def _read(self, pair: _Pair, wait: bool) -> None:
        if wait:
            pair.end.synchronize()
        self._totals[pair.stage] += pair.start.elapsed_time(pair.end) / 1e3
        self._pool += (pair.start, pair.end)
