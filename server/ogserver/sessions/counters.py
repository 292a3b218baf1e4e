"""What a session has counted, read as one consistent record for its stats and its listing."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SessionCounters:
    received: int  # frames accepted into the queue
    rejected: int  # frames refused before the queue (validation, anchor limit)
    mapped: int
    pending: int  # queued or being mapped
    skipped: int  # realtime sessions: recorded and acknowledged, but passed over for a newer frame
    anchors: int  # the map's anchors after the last mapped frame
    processing_fps: float  # mapped frames over the time from the first received to the last mapped
    uptime_seconds: float
    # Over the whole session, across resumes: the last frame accepted (mapped or queued to be, in
    # order; a resumed stream sends the frames after it), its Frame.index, and the last one mapped.
    last_sequence: int = 0
    last_index: int = 0
    mapped_sequence: int = 0


@dataclass(frozen=True)
class FrameTotals:
    """Frames over sessions, for counters that only grow (metrics): open sessions plus closed ones."""

    received: int = 0
    rejected: int = 0
    mapped: int = 0
    unmapped: int = 0  # received but never mapped: skipped (realtime), the mapper failed on it, or the session closed

    @classmethod
    def of(cls, counters: SessionCounters) -> FrameTotals:
        return cls(counters.received, counters.rejected, counters.mapped,
                   counters.received - counters.mapped - counters.pending)

    def __add__(self, other: FrameTotals) -> FrameTotals:
        return FrameTotals(self.received + other.received, self.rejected + other.rejected,
                           self.mapped + other.mapped, self.unmapped + other.unmapped)


def rate(count: int, first: float | None, last: float | None) -> float:
    """``count`` events a second between the monotonic times ``first`` and ``last`` (0 before both are known)."""
    elapsed = last - first if first is not None and last is not None else 0.0
    return count / elapsed if elapsed > 0 else 0.0
