"""kill -9 in the middle of a frame stream: the next server on the record dir resumes the session with
the same id and token, loses no acknowledged frame, `ogclient stream --resume` sends only the frames
after the last one it has, and the map renders what an uninterrupted session of the same frames
renders (to replay's tolerance, as in test_compatibility)."""

from __future__ import annotations

import re
from pathlib import Path

import grpc
import numpy as np
import pytest
from ogapi import recording
from ogapi.v1 import mapping_pb2 as pb
from ogclient.__main__ import main as ogclient_main
from ogclient.connection import SessionRef, connect
from ogclient.evaluation import render
from ogclient.messages import frame_to_proto

from ogmapping.quality.evaluation import open_frames
from ogmapping.quality.metrics import psnr

from .conftest import start_local
from .scene import PRESET, TINY, create_request

SERVER_ARGS = ("--checkpoint-interval", "2", "--no-warm-up")
# What `ogclient stream --data synthetic --format synthetic --frames 0:10 --scale 0.25` sends.
DATASET = ["--data", "synthetic", "--format", "synthetic", "--frames", "0:10", "--scale", "0.25"]
KILL_AFTER = 4  # acks: two checkpoints written, frames still queued and one being mapped


def stats(stub, session: SessionRef) -> pb.Stats:
    return stub.GetStats(pb.GetStatsRequest(session_id=session.session_id), metadata=session.metadata())


def stream_until_killed(address: str, session: SessionRef, server) -> list[pb.FrameAck]:
    frames = open_frames("synthetic", "synthetic", "0:10", 1, 0.25)
    messages = (frame_to_proto(frames.load(position)) for position in frames.selection.streamed)
    channel, stub = connect(address, timeout=60.0)
    acked: list[pb.FrameAck] = []
    responses = stub.StreamFrames(messages, metadata=session.stream_metadata())
    try:
        for ack in responses:
            acked.append(ack)
            if len(acked) == KILL_AFTER:
                server.kill()  # frames 5 and on are queued, being mapped or still on their way
                break
    finally:
        responses.cancel()
        channel.close()
    return acked


def test_a_session_survives_kill_9_mid_stream(tmp_path: Path) -> None:
    record_dir = tmp_path / "recordings"
    first = start_local(record_dir, *SERVER_ARGS)
    channel, stub = connect(first.address, timeout=60.0)
    session = SessionRef.from_credentials(stub.CreateSession(create_request(TINY, "crash")))
    channel.close()
    acked = stream_until_killed(first.address, session, first)
    assert len(acked) == KILL_AFTER and all(ack.accepted for ack in acked)
    assert first.process.returncode == -9

    second = start_local(record_dir, *SERVER_ARGS)
    try:
        channel, stub = connect(second.address, timeout=60.0)
        with pytest.raises(grpc.RpcError) as refusal:  # the token is still checked
            stub.GetStats(pb.GetStatsRequest(session_id=session.session_id),
                          metadata=(("x-session-token", "x" * 43),))
        assert refusal.value.code() == grpc.StatusCode.UNAUTHENTICATED
        resumed_from = re.search(r"resumed for \S+ from its checkpoint at frame (\d+)", second.log_path.read_text())
        assert resumed_from and int(resumed_from.group(1)) >= 2, "not resumed from a periodic checkpoint"
        standing = stats(stub, session)  # same id, same token
        assert standing.last_sequence >= KILL_AFTER, "an acknowledged frame was lost"
        assert standing.last_index >= acked[-1].index

        session_file = tmp_path / "session.json"
        session.save(session_file, second.address)
        assert ogclient_main(["--server", second.address, "stream", *DATASET, "--session", str(session_file),
                              "--resume", "--quiet"]) == 0
        done = stats(stub, session)
        assert done.last_sequence == done.mapped_sequence == 9  # the 9 streamed positions, each once

        uninterrupted_file = tmp_path / "uninterrupted.json"
        assert ogclient_main(["--server", second.address, "stream", *DATASET, "--preset", PRESET,
                              *(item for key, value in TINY.items() for item in ("--set", f"{key}={value}")),
                              "--session-out", str(uninterrupted_file), "--quiet"]) == 0
        held_out = open_frames("synthetic", "synthetic", "0:10", 1, 0.25).load(5)
        resumed = render(stub, session, held_out.c2w, held_out.color_intrinsics)
        reference = render(stub, SessionRef.load(uninterrupted_file), held_out.c2w, held_out.color_intrinsics)
        assert psnr(resumed.color, reference.color) > 40.0, "the resumed map differs from the uninterrupted one"
        assert np.abs(resumed.depth - reference.depth).mean() < 0.01

        stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id), metadata=session.metadata())
        channel.close()
    finally:
        second.stop()
    recorded = recording.load(record_dir / f"{session.session_id}.mcap")
    indices = [frame.index for _, frame in recorded.frames]
    assert indices == [0, 1, 2, 3, 4, 6, 7, 8, 9], "the recording holds a frame twice, or misses one"
    assert {ack.index for ack in acked} <= set(indices)
