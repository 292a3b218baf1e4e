"""Realtime sessions: a 30 FPS sender against a slower map keeps its rate, every frame is acknowledged,
and the frames passed over are in the recording, where a replay maps them, as far as the session's
budget for recording them goes."""

from __future__ import annotations

import queue
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from ogapi import recording
from ogapi.v1 import mapping_pb2 as pb
from ogclient import replay
from ogclient.__main__ import main as ogclient_main
from ogclient.connection import SessionRef
from ogclient.streaming import paced, stream_frames
from ogserver.access.callers import ANONYMOUS
from ogserver.api.validation import frame as validate_frame
from ogserver.recording.recorder import frame_record
from ogserver.sessions.registry import Registry
from ogserver.settings import Settings

from ogmapping.config import OctreeConfig

from .held_mapper import flood_while_held, frame_messages
from .inprocess import serving, settings
from .scene import FROZEN, create_request, messages, scene

FPS = 30.0
# Every frame optimises 8 iterations: far slower than 30 FPS on a CPU, so frames must be skipped.
SLOW = {"keyframes.first_iterations": "8", "keyframes.iterations": "8", "keyframes.frame_iterations": "8"}
SETS = [item for key, value in SLOW.items() for item in ("--set", f"{key}={value}")]


def sensor(frames: list[pb.Frame], count: int, sent: list[float]) -> Iterator[pb.Frame]:
    """``count`` frames cycling through ``frames`` (each its own index), at 30 FPS; ``sent`` gets the
    time each one was taken by gRPC."""
    cycle = (frames[number % len(frames)] for number in range(count))
    for number, frame in enumerate(paced(cycle, FPS)):
        sent.append(time.monotonic())
        message = pb.Frame()
        message.CopyFrom(frame)
        message.index = number
        yield message


def test_a_realtime_stream_keeps_its_rate_and_records_skipped_frames(tmp_path) -> None:
    count = 45
    frames = messages(scene("0:20"))
    sent: list[float] = []
    with serving(settings(tmp_path)) as running:
        request = create_request(SLOW)
        request.realtime = True
        credentials = running.stub.CreateSession(request)
        session = SessionRef.from_credentials(credentials)
        result = stream_frames(running.stub, session, sensor(frames, count, sent), progress=False)
        stats = running.stub.GetStats(pb.GetStatsRequest(session_id=session.session_id), metadata=session.metadata())
        running.stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id), metadata=session.metadata())

    # The sender kept its own rate: the server never held a frame back.
    span = sent[-1] - sent[0]
    assert span < (count - 1) / FPS + 0.5, f"{count} frames took {span:.2f} s to send at {FPS:g} FPS"
    # Every frame was acknowledged, most of them as skipped, the rest mapped.
    assert sorted(ack.index for ack in result.acks) == list(range(count))
    assert not result.rejected
    assert result.skipped and result.mapped and len(result.skipped) + len(result.mapped) == count
    assert all(ack.accepted and ack.iterations == 0 and not ack.keyframe for ack in result.skipped)
    assert sorted(ack.sequence for ack in result.acks) == list(range(1, count + 1))
    # Latency stays bounded: a frame waits at most for the one being mapped (plus its own mapping).
    slowest = max(ack.process_seconds for ack in result.mapped)
    assert max(ack.latency_seconds for ack in result.acks) < 2 * slowest + 1.0
    assert stats.frames_skipped == len(result.skipped) and stats.frames == len(result.mapped)
    assert stats.frames_received == count

    # The recording holds every frame in arrival order, with the same acks; a replay maps them all.
    recorded = recording.load(Path(settings(tmp_path).record_dir) / credentials.recording)
    assert recorded.config.realtime
    assert [frame.index for _, frame in recorded.frames] == list(range(count))
    assert {ack.index for ack in recorded.acks if ack.skipped} == {ack.index for ack in result.skipped}
    assert not replay.session_request(recorded.config).realtime



def test_ogclient_streams_a_realtime_session_at_a_rate(tmp_path, capsys) -> None:
    session_file = tmp_path / "session.json"
    with serving(settings(tmp_path)) as running:
        base = ["--server", running.address, "stream", "--data", "synthetic", "--format", "synthetic",
                "--frames", "0:10", "--scale", "0.25", "--preset", "sparse-fast", "--quiet"]
        assert ogclient_main([*base, *SETS, "--realtime", "--fps", "30", "--session-out", str(session_file)]) == 0
        summary = capsys.readouterr().out
        session = SessionRef.load(session_file)
        stats = running.stub.GetStats(pb.GetStatsRequest(session_id=session.session_id), metadata=session.metadata())
        assert f"{stats.frames} frames mapped" in summary and f"{stats.frames_skipped} skipped" in summary
        assert stats.frames + stats.frames_skipped == stats.frames_received == 9
        # Realtime is chosen at creation: an existing session cannot be switched.
        assert ogclient_main([*base, "--realtime", "--session", str(session_file)]) == 2
        assert "--realtime is chosen when the session is created" in capsys.readouterr().err
        # The replay of the recording maps every frame, the skipped ones too.
        running.stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id), metadata=session.metadata())
        recorded = running.record_dir / f"{session.session_id}.mcap"
        assert ogclient_main(["--server", running.address, "replay", str(recorded), "--quiet",
                              "--session-out", str(tmp_path / "replayed.json")]) == 0
        out = capsys.readouterr().out
        assert f"realtime and skipped {stats.frames_skipped} of its frames" in out
        assert "9 frames mapped (" in out and " 0 skipped" in out


# ---------------------------------------------------------------------------- what skipped frames cost the disk


def flooded(tmp_path, total: int, per_second: int, count: int) -> tuple[list[pb.FrameAck], recording.Recording, float]:
    """A realtime session's first frame held while ``count - 1`` more flood in: its acks, its recording
    and how long the flood took."""
    configured = Settings(record_dir=str(tmp_path), checkpoint_interval=0)
    configured.limits.max_skipped_recording_bytes = total
    configured.limits.skipped_recording_bytes_per_second = per_second
    registry = Registry(configured, "cpu")
    request = create_request(FROZEN)
    request.realtime = True
    opened = registry.create(request, ANONYMOUS)
    sink: queue.SimpleQueue = queue.SimpleQueue()
    started = time.monotonic()
    held = flood_while_held(opened.session, frame_messages(count), sink)
    elapsed = time.monotonic() - started
    held.release()
    held.taken()
    held.release()
    acks = [sink.get(timeout=60).ack for _ in range(count)]
    closed = registry.close(opened.session)
    return acks, recording.load(closed.recording), elapsed


def recorded_size(message: pb.Frame) -> int:
    return frame_record(message, validate_frame(message, 1 << 20, OctreeConfig()), 0).size


def test_a_flooded_realtime_session_records_skipped_frames_within_its_budget(tmp_path) -> None:
    size = max(recorded_size(message) for message in frame_messages(12))
    acks, recorded, _ = flooded(tmp_path, total=2 * size + size // 2, per_second=1 << 40, count=12)
    # Frame 0 and 11 mapped; of the 10 skipped, the first two fit the budget and are recorded.
    assert [frame.index for _, frame in recorded.frames] == [0, 1, 2, 11]
    by_index = {ack.index: ack for ack in acks}
    assert all(ack.accepted and ack.skipped and ack.unrecorded and ack.sequence == 0
               for index, ack in by_index.items() if 3 <= index <= 10)
    assert [by_index[index].sequence for index in (0, 1, 2, 11)] == [1, 2, 3, 4]
    assert not any(by_index[index].unrecorded for index in (0, 1, 2, 11))
    assert {ack.index for ack in recorded.acks if ack.skipped} == {1, 2}  # unrecorded acks are not recorded
    assert recorded.stats is not None and recorded.stats.frames_skipped == 10
    assert recorded.stats.last_sequence == 4


def test_a_flooded_realtime_session_records_skipped_frames_at_its_rate(tmp_path) -> None:
    size = max(recorded_size(message) for message in frame_messages(40))
    rate = 2 * size  # two skipped frames a second, one second's worth at once
    acks, recorded, elapsed = flooded(tmp_path, total=1 << 40, per_second=rate, count=40)
    skipped_recorded = [frame for _, frame in recorded.frames if frame.index not in (0, 39)]
    assert len(skipped_recorded) * size <= rate * (1 + elapsed), f"{len(skipped_recorded)} in {elapsed:.2f} s"
    assert len(skipped_recorded) >= 2  # the first second's worth
    assert sum(ack.unrecorded for ack in acks) == 38 - len(skipped_recorded)


def test_skipped_frames_can_be_left_out_of_recordings() -> None:
    configured = Settings()
    configured.limits.max_skipped_recording_bytes = configured.limits.skipped_recording_bytes_per_second = 0
    configured.validate()
    configured.limits.skipped_recording_bytes_per_second = -1
    with pytest.raises(ValueError, match="skipped_recording_bytes_per_second is out of range: must be >= 0, got -1"):
        configured.validate()
