"""A session in-process: the anchor limit, and closing with frames still queued."""

from __future__ import annotations

import queue
from pathlib import Path

import grpc
import pytest
from ogapi.v1 import mapping_pb2 as pb
from ogclient.messages import frame_to_proto
from ogserver.errors import ServiceError
from ogserver.events import Acked, SessionClosed
from ogserver.recorder import Recorder
from ogserver.session import Session
from ogserver.settings import Limits
from ogserver.validation import frame as validate_frame

from ogmapping.config import OctreeConfig, resolve
from ogmapping.mapper import Mapper

from .scene import FROZEN, PRESET, scene


def make_session(tmp_path: Path, limits: Limits) -> Session:
    config = pb.SessionConfig(session_id="1" * 32, preset=PRESET)
    recorder = Recorder(tmp_path / "session.mcap", config)
    return Session(config, "token", Mapper(resolve(PRESET, overrides=FROZEN)), recorder, limits)


def submit(session: Session, position: int, sink: queue.SimpleQueue) -> None:
    message = frame_to_proto(scene("0:8").load(position))
    assert session.submit(validate_frame(message, 1 << 20, OctreeConfig()), message, sink)


def test_anchor_limit_refuses_further_frames(tmp_path: Path) -> None:
    session = make_session(tmp_path, Limits(max_anchors=10))
    sink: queue.SimpleQueue = queue.SimpleQueue()
    try:
        session.check_capacity()
        submit(session, 0, sink)
        event = sink.get(timeout=60)
        assert isinstance(event, Acked) and event.ack.accepted and event.ack.anchors > 10
        with pytest.raises(ServiceError) as refusal:
            session.check_capacity()
        assert refusal.value.code == grpc.StatusCode.RESOURCE_EXHAUSTED and "anchors" in refusal.value.message
    finally:
        session.close()
        session.recorder.close()


def test_close_drops_queued_frames_and_ends_the_stream(tmp_path: Path) -> None:
    session = make_session(tmp_path, Limits(queue_depth=8))
    sink: queue.SimpleQueue = queue.SimpleQueue()
    with session.stream(sink):
        for position in range(4):
            submit(session, position, sink)
        session.close()
        events = []
        while not sink.empty():
            events.append(sink.get())
    counters = session.counters()
    assert isinstance(events[-1], SessionClosed)
    assert sum(isinstance(event, Acked) for event in events) == counters.mapped <= 4
    assert counters.pending == 0
    frame = validate_frame(frame_to_proto(scene("0:1").load(0)), 1 << 20, OctreeConfig())
    assert not session.submit(frame, pb.Frame(), None)
    session.recorder.close()
