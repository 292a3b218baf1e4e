"""One frame's optimisation has a wall-clock budget, and closing its session interrupts it."""

from __future__ import annotations

import queue
import time
from pathlib import Path

import grpc
from ogapi.v1 import mapping_pb2 as pb
from ogclient.messages import frame_to_proto
from ogserver.api.validation import frame as validate_frame
from ogserver.recording.recorder import Recorder
from ogserver.sessions.session import Session
from ogserver.sessions.stream_events import Acked
from ogserver.settings import Limits

from ogmapping.config import resolve
from ogmapping.mapper import Mapper

from .scene import PRESET, scene

LONG = {"keyframes.first_iterations": "500"}  # within the default bounds, many seconds on a CPU


def long_session(tmp_path: Path, frame_seconds: float) -> Session:
    config = pb.SessionConfig(session_id="2" * 32, preset=PRESET)
    mapper = Mapper(resolve(PRESET, overrides=LONG))
    return Session(config, "token", mapper, Recorder(tmp_path / "session.mcap", config), Limits(), frame_seconds)


def submit_first_frame(session: Session, sink: queue.SimpleQueue) -> None:
    message = frame_to_proto(scene("0:1").load(0))
    assert session.submit(validate_frame(message, 1 << 20, session.mapper.config.octree), message, sink)


def test_close_interrupts_the_frame_being_mapped(tmp_path: Path) -> None:
    """CloseSession (and so shutdown) once waited for every iteration of the frame being mapped."""
    session = long_session(tmp_path, frame_seconds=0.0)
    sink: queue.SimpleQueue = queue.SimpleQueue()
    submit_first_frame(session, sink)
    deadline = time.monotonic() + 60
    # The counter itself, not stats(): stats() waits for the mapper's lock, which the mapping
    # thread takes again straight after each step, so it could return only after the whole frame.
    while session.mapper.model.iterations == 0 and time.monotonic() < deadline:
        time.sleep(0.05)
    start = time.monotonic()
    session.close()
    assert time.monotonic() - start < 5
    event = sink.get(timeout=5)
    assert isinstance(event, Acked) and event.ack.accepted and 0 < event.ack.iterations < 500
    assert event.ack.error.code_name == grpc.StatusCode.CANCELLED.name
    assert "stopped after" in event.ack.error.message
    session.recorder.close()


def test_a_frame_over_its_budget_ends_early_and_its_ack_says_so(tmp_path: Path) -> None:
    session = long_session(tmp_path, frame_seconds=1.0)
    sink: queue.SimpleQueue = queue.SimpleQueue()
    try:
        submit_first_frame(session, sink)
        event = sink.get(timeout=60)
        assert isinstance(event, Acked) and event.ack.accepted and event.ack.iterations < 500
        assert event.ack.error.code_name == grpc.StatusCode.DEADLINE_EXCEEDED.name
        assert "frame_seconds" in event.ack.error.message and event.ack.process_seconds < 10
    finally:
        session.close()
        session.recorder.close()
