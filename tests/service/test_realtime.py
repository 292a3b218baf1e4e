"""Realtime sessions: a 30 FPS sender against a slower map keeps its rate, every frame is acknowledged,
and the frames passed over are in the recording, where a replay maps them."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

from ogapi import recording
from ogapi.v1 import mapping_pb2 as pb
from ogclient import replay
from ogclient.__main__ import main as ogclient_main
from ogclient.connection import SessionRef
from ogclient.streaming import paced, stream_frames

from .inprocess import serving, settings
from .scene import create_request, messages, scene

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
