"""A session's mapper held at each frame until the test releases it: which frames a realtime session
maps and which it skips is then certain, not a matter of timing."""

from __future__ import annotations

import queue
import threading

from ogapi.v1 import mapping_pb2 as pb
from ogclient.messages import frame_to_proto
from ogserver.api.validation import frame as validate_frame
from ogserver.sessions.session import Session

from ogmapping.config import OctreeConfig

from .scene import scene


class HeldMapper:
    """Replaces ``session.mapper.process``; ``taken()`` waits until the worker holds a frame."""

    def __init__(self, session: Session) -> None:
        self._process = session.mapper.process
        self._taken = threading.Semaphore(0)
        self._released = threading.Semaphore(0)
        session.mapper.process = self  # type: ignore[method-assign]

    def __call__(self, frame, budget=None):
        self._taken.release()
        assert self._released.acquire(timeout=60), "the test never released the frame"
        return self._process(frame, budget)

    def taken(self) -> None:
        assert self._taken.acquire(timeout=60), "the worker took no frame"

    def release(self) -> None:
        self._released.release()


def frame_messages(count: int) -> list[pb.Frame]:
    """``count`` frames cycling through the tiny scene, numbered 0, 1, ..."""
    source = scene("0:8")
    frames = [frame_to_proto(source.load(position)) for position in source.selection.streamed]
    result = []
    for number in range(count):
        message = pb.Frame()
        message.CopyFrom(frames[number % len(frames)])
        message.index = number
        result.append(message)
    return result


def submit(session: Session, message: pb.Frame, sink: queue.SimpleQueue) -> None:
    assert session.submit(validate_frame(message, 1 << 20, OctreeConfig()), message, sink)


def flood_while_held(session: Session, messages: list[pb.Frame], sink: queue.SimpleQueue) -> HeldMapper:
    """The first frame is taken up and held; the others arrive meanwhile, so a realtime session
    (queue depth 1) skips all but the last, which it maps once the test releases the first."""
    held = HeldMapper(session)
    submit(session, messages[0], sink)
    held.taken()
    for message in messages[1:]:
        submit(session, message, sink)
    return held
