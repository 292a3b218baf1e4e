"""What a session has counted, read as one consistent record for its stats and its listing."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SessionCounters:
    received: int  # frames accepted into the queue
    rejected: int  # frames refused before the queue (validation, anchor limit)
    mapped: int
    pending: int  # queued or being mapped
    anchors: int  # the map's anchors after the last mapped frame
    processing_fps: float  # mapped frames over the time from the first received to the last mapped
    uptime_seconds: float
