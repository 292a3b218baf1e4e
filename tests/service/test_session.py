"""A session in-process: the anchor limit, closing with frames still queued, a recording that fails."""

from __future__ import annotations

import queue
import threading
from pathlib import Path

import grpc
import pytest
from ogapi import recording
from ogapi.v1 import mapping_pb2 as pb
from ogclient.messages import frame_to_proto
from ogserver.access.tokens import TokenHash
from ogserver.api.validation import frame as validate_frame
from ogserver.errors import ServiceError
from ogserver.recording.recorder import Recorder
from ogserver.sessions.session import Session
from ogserver.sessions.stream_events import Acked, SessionClosed
from ogserver.settings import Limits

from ogmapping.config import OctreeConfig, resolve
from ogmapping.mapper import Mapper

from .conftest import FullDisk
from .scene import FROZEN, PRESET, TINY, scene


def make_session(tmp_path: Path, limits: Limits, overrides: dict[str, str] = FROZEN) -> Session:
    config = pb.SessionConfig(session_id="1" * 32, preset=PRESET)
    recorder = Recorder(tmp_path / "session.mcap", config)
    return Session(config, TokenHash.of("token"), Mapper(resolve(PRESET, overrides=overrides)), recorder, limits)


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


def test_close_drops_queued_frames_unrecorded_so_a_replay_maps_the_same(tmp_path: Path) -> None:
    """The recording holds the frames the session mapped, not the ones it dropped at close."""
    session = make_session(tmp_path, Limits(queue_depth=8), TINY)
    sink: queue.SimpleQueue = queue.SimpleQueue()
    for position in range(6):
        submit(session, position, sink)
    assert isinstance(sink.get(timeout=60), Acked)  # the first is mapped, most of the rest still queued
    session.close()
    mapped = session.counters().mapped
    stats = session.map_stats()
    session.recorder.close()
    recorded = recording.load(session.recorder.path)
    assert mapped < 6 and len(recorded.frames) == len(recorded.acks) == mapped
    replay = Mapper(resolve(PRESET, overrides=TINY))
    for _, message in recorded.frames:
        replay.process(validate_frame(message, 1 << 20, OctreeConfig()))
    assert replay.stats().frames == stats.frames
    # Closing also stops the frame being mapped between two iterations (its ack says CANCELLED);
    # a replay maps that frame in full, so only a session that closed between frames rebuilds the
    # same anchors (docs/service.md, Replay).
    if not any(ack.error.code_name == "CANCELLED" for ack in recorded.acks):
        assert replay.stats().anchors == stats.anchors


def test_a_failing_recording_answers_every_frame_and_returns_its_slots(tmp_path: Path, full_disk: FullDisk) -> None:
    session = make_session(tmp_path, Limits(queue_depth=2))
    sink: queue.SimpleQueue = queue.SimpleQueue()
    submit(session, 0, sink)
    assert sink.get(timeout=60).ack.accepted
    full_disk.free = 0

    def submit_more() -> None:  # more frames than the queue holds: leaked slots would block here
        for position in range(1, 6):
            submit(session, position, sink)

    submitter = threading.Thread(target=submit_more, daemon=True)
    submitter.start()
    submitter.join(timeout=60)
    assert not submitter.is_alive()
    acks = [sink.get(timeout=60).ack for _ in range(5)]
    try:
        assert [ack.index for ack in acks] == [1, 2, 3, 4, 5] and not any(ack.accepted for ack in acks)
        assert {ack.error.code_name for ack in acks} == {"RESOURCE_EXHAUSTED"}
        assert "recording" in acks[0].error.message
        with pytest.raises(ServiceError) as refusal:  # what the stream's reader asks before queueing more
            session.check_capacity()
        assert refusal.value.code == grpc.StatusCode.RESOURCE_EXHAUSTED
        counters = session.counters()
        assert (counters.mapped, counters.pending) == (1, 0)
    finally:
        session.close()
    full_disk.free = None
    session.recorder.close()
    assert len(recording.load(session.recorder.path).frames) == 1


def test_a_defect_while_reading_a_stream_ends_it_with_internal_not_silently() -> None:
    from ogserver.api import stream
    from ogserver.sessions.stream_events import ReaderDone

    class Broken:
        id = "0" * 32

        def check_capacity(self) -> None:
            raise RuntimeError("a programming error")

    sink: queue.SimpleQueue = queue.SimpleQueue()
    stream._read(Broken(), [frame_to_proto(scene("0:1").load(0))], sink, 1 << 20)  # type: ignore[arg-type]
    done = sink.get_nowait()
    assert isinstance(done, ReaderDone) and done.error is not None
    assert done.error.code == grpc.StatusCode.INTERNAL


def test_queued_frames_are_prepared_ahead_and_map_in_order(tmp_path: Path) -> None:
    """While the worker maps a frame, the next queued one is prepared on the session's second thread:
    every frame is acknowledged in order, and the stage timers count that work off the mapping path."""
    session = make_session(tmp_path, Limits(queue_depth=8), TINY)
    sink: queue.SimpleQueue = queue.SimpleQueue()
    try:
        with session.mapper.lock:  # the first frame waits to map while the others queue up behind it
            for position in range(4):
                submit(session, position, sink)
        acks = [sink.get(timeout=120) for _ in range(4)]
        assert [event.ack.index for event in acks] == [scene("0:8").load(p).index for p in range(4)]
        assert all(event.ack.accepted for event in acks)
        timings = session.map_stats().timings
        assert timings.get("preprocess_ahead", 0.0) > 0, timings
    finally:
        session.close()
        session.recorder.close()
