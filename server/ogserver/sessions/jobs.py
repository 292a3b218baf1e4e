"""A session's queued frames: what each carries to the worker, and its preparation ahead of mapping."""

from __future__ import annotations

import queue
from collections import deque
from concurrent.futures import Executor, Future
from dataclasses import dataclass

from ogmapping.frames.frame import Frame
from ogmapping.mapper import Mapper, PreparedFrame
from ogserver.recording.recorder import FrameRecord
from ogserver.sessions.stream_events import StreamEvent


@dataclass
class Job:
    frame: Frame
    record: FrameRecord
    sequence: int  # its place among the session's recorded frames
    received: float  # time.monotonic() when the frame was read
    sink: queue.SimpleQueue[StreamEvent] | None  # where the stream that sent it waits for its ack
    size: int  # bytes it holds of the session's max_queued_bytes (0 in a realtime session, which holds none)
    prepared: Future[PreparedFrame] | None = None  # made ready to map while the frame before it mapped


def prepare_next(jobs: deque[Job | None], preparer: Executor, mapper: Mapper) -> None:
    """Start preparing the next queued frame (``Mapper.prepare``) while the one just taken maps."""
    upcoming = jobs[0] if jobs else None
    if upcoming is not None and upcoming.prepared is None:
        upcoming.prepared = preparer.submit(mapper.prepare, upcoming.frame)
