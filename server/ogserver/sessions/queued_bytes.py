"""The bytes of decoded frames one session may hold queued (``max_queued_bytes``).

A frame that does not fit waits, like one over ``queue_depth``, so the stream's reader stops and
gRPC flow control holds the client back. A frame always fits into an empty budget, so a budget
smaller than one frame slows a session to one frame at a time instead of stopping it.
"""

from __future__ import annotations

import threading

from ogmapping.frames.frame import Frame

POLL_SECONDS = 0.2


def frame_bytes(frame: Frame) -> int:
    return frame.rgb.nbytes + frame.depth.nbytes


class ByteBudget:
    def __init__(self, limit: int) -> None:
        self.limit = limit
        self._held = 0
        self._changed = threading.Condition()

    def acquire(self, size: int, cancelled: threading.Event) -> bool:
        """Wait until ``size`` fits; False (nothing taken) once ``cancelled`` is set."""
        with self._changed:
            while self._held and self._held + size > self.limit:
                if cancelled.is_set():
                    return False
                self._changed.wait(POLL_SECONDS)
            self._held += size
            return True

    def release(self, size: int) -> None:
        with self._changed:
            self._held -= size
            self._changed.notify_all()
