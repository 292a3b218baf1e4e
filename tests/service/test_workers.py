"""Sessions in worker processes (``ogserver --workers 2``): the same service as threads of one process.

Sessions go to the least-loaded worker and map side by side; create, stream, render, stats, snapshot and
close work through the workers; refusals carry the same status and message as a threaded server's;
max_sessions and each caller's quota count every worker's sessions, idle ones expire in their worker;
two sessions streaming at once lose and reorder nothing and both recordings replay. A worker killed with
SIGKILL mid-stream costs only its own session (UNAVAILABLE, naming why), the other worker's session maps
on, and a server restarted with ``--resume`` brings the lost one back with every acknowledged frame.
"""

from __future__ import annotations

import os
import re
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import grpc
import numpy as np
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from ogapi import API_KEY_METADATA_KEY, recording
from ogapi.v1 import mapping_pb2 as pb
from ogclient.__main__ import main as ogclient_main
from ogclient.connection import SessionRef, connect
from ogclient.evaluation import render, snapshot_bytes
from ogclient.local_server import LocalServer
from ogserver.apikeys import digest

from ogmapping.mapper import Mapper

from .bad_frames import CASES, broken
from .conftest import start_local
from .scene import FROZEN, TINY, create_request, messages, scene

WORKERS = ("--workers", "2", "--no-warm-up")
PLACED = re.compile(r"session (\w+) placed on worker (\d+) \(pid (\d+)\)")
SERVING = re.compile(r"worker \d+ \(pid (\d+)\) serving")


@pytest.fixture(scope="module")
def workers(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalServer]:
    server = start_local(tmp_path_factory.mktemp("workers"), *WORKERS)
    try:
        yield server
    finally:
        server.stop()


def placements(server: LocalServer) -> dict[str, int]:
    """Session id -> the pid of the worker it was placed on, from the server's log."""
    return {found[0]: int(found[2]) for found in PLACED.findall(server.log_path.read_text())}


def stats(stub, session: SessionRef) -> pb.Stats:
    return stub.GetStats(pb.GetStatsRequest(session_id=session.session_id), metadata=session.metadata())


class Streaming(threading.Thread):
    """One session's frames streamed from a thread; its acks, and the error that ended it, if any."""

    def __init__(self, stub, session: SessionRef, frames: list[pb.Frame], after_ack=None) -> None:
        super().__init__(daemon=True)
        self.stub, self.session, self.frames, self.after_ack = stub, session, frames, after_ack
        self.acks: list[pb.FrameAck] = []
        self.error: grpc.RpcError | None = None

    def run(self) -> None:
        try:
            for ack in self.stub.StreamFrames(iter(self.frames), metadata=self.session.stream_metadata()):
                self.acks.append(ack)
                if self.after_ack is not None:
                    self.after_ack(len(self.acks))
        except grpc.RpcError as error:
            self.error = error


def stream_both(stub, sessions: list[SessionRef], frames: list[list[pb.Frame]], after_ack=None) -> list[Streaming]:
    streams = [Streaming(stub, session, sent, after_ack if number == 0 else None)
               for number, (session, sent) in enumerate(zip(sessions, frames, strict=True))]
    for stream in streams:
        stream.start()
    for stream in streams:
        stream.join(timeout=300)
        assert not stream.is_alive(), "a stream did not end"
    return streams


def test_two_sessions_map_in_two_workers_and_replay(workers: LocalServer, tmp_path: Path) -> None:
    channel, stub = connect(workers.address, timeout=60.0)
    sessions = [SessionRef.from_credentials(stub.CreateSession(create_request(TINY, label))) for label in "ab"]
    placed = placements(workers)
    assert len({placed[session.session_id] for session in sessions}) == 2, "both sessions on one worker"
    frame_sets = [scene(), scene("20:30")]
    sent = [messages(frames) for frames in frame_sets]
    streams = stream_both(stub, sessions, sent)
    for stream, frames in zip(streams, frame_sets, strict=True):
        assert stream.error is None
        assert [ack.index for ack in stream.acks] == frames.selection.streamed  # nothing lost or reordered
        assert [ack.sequence for ack in stream.acks] == list(range(1, len(stream.acks) + 1))
        assert all(ack.accepted for ack in stream.acks)
        assert stats(stub, stream.session).frames == len(frames.selection.streamed)

    first = streams[0].acks[0]
    corrected = np.array(sent[0][0].c2w, dtype=np.float64).reshape(4, 4)
    corrected[:3, 3] += (0.02, 0.0, -0.01)
    request = pb.CorrectPosesRequest(session_id=sessions[0].session_id, poses=[
        pb.CorrectedPose(sequence=first.sequence, c2w=corrected.reshape(-1).tolist())])
    moved = stub.CorrectPoses(request, metadata=sessions[0].metadata())
    assert moved.keyframes == 1 and moved.anchors_moved > 0, "a correction through a worker moves the map"

    held_out = frame_sets[0].load(5)
    rendered = render(stub, sessions[0], held_out.c2w, held_out.color_intrinsics)
    assert rendered.color.shape == (held_out.color_intrinsics.height, held_out.color_intrinsics.width, 3)
    assert rendered.color.std() > 0 and np.all(rendered.depth >= 0)
    snapshot = snapshot_bytes(stub, sessions[1])
    assert Mapper.restore(snapshot, device="cpu").stats().anchors == stats(stub, sessions[1]).anchors
    restored = SessionRef.from_credentials(stub.RestoreSession(iter([pb.RestoreChunk(data=snapshot, label="r")])))
    assert stats(stub, restored).anchors == stats(stub, sessions[1]).anchors
    stub.CloseSession(pb.CloseSessionRequest(session_id=restored.session_id), metadata=restored.metadata())
    listed = stub.ListSessions(pb.ListSessionsRequest()).sessions
    assert {item.session_id for item in listed} == {session.session_id for session in sessions}

    for session, frames in zip(sessions, sent, strict=True):
        closed = stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id), metadata=session.metadata())
        assert closed.stats.frames == len(frames)
        path = workers.record_dir / closed.recording
        recorded = recording.load(path)
        assert [frame.SerializeToString() for _, frame in recorded.frames] == \
            [frame.SerializeToString() for frame in frames], "the recording's frames are not the frames sent"
        assert ogclient_main(["--server", workers.address, "replay", str(path), "--quiet", "--close",
                              "--session-out", str(tmp_path / f"{session.session_id}.json")]) == 0
    with pytest.raises(grpc.RpcError) as gone:
        stats(stub, sessions[0])
    assert gone.value.code() == grpc.StatusCode.NOT_FOUND
    channel.close()


def refusals(address: str) -> list[tuple[grpc.StatusCode, str]]:
    """What a server answers to bad frames, a wrong token, an unknown session and a bad CreateSession."""
    channel, stub = connect(address, timeout=60.0)
    session = SessionRef.from_credentials(stub.CreateSession(create_request(FROZEN, "refusals")))
    good = messages(scene("0:1"))[0]
    bad = [broken(good, change) for change, _, _ in CASES.values()]
    acks = list(stub.StreamFrames(iter([*bad, good]), metadata=session.stream_metadata()))
    answers = [(grpc.StatusCode[ack.error.code_name] if ack.error.code_name else grpc.StatusCode.OK,
                ack.error.message) for ack in acks]
    calls = [
        lambda: stub.GetStats(pb.GetStatsRequest(session_id=session.session_id),
                              metadata=(("x-session-token", "x" * 43),)),
        lambda: stub.GetStats(pb.GetStatsRequest(session_id="0" * 32), metadata=session.metadata()),
        lambda: stub.GetStats(pb.GetStatsRequest(session_id="not-an-id"), metadata=session.metadata()),
        lambda: stub.CreateSession(pb.CreateSessionRequest(preset="no-such-preset")),
        lambda: stub.CreateSession(create_request({"keyframes.iterations": "-1"})),
        lambda: next(stub.StreamFrames(iter([good]), metadata=(("x-session-id", session.session_id),
                                                               ("x-session-token", "x" * 43)))),
    ]
    for call in calls:
        with pytest.raises(grpc.RpcError) as refused:
            call()
        answers.append((refused.value.code(), refused.value.details()))
    stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id), metadata=session.metadata())
    with pytest.raises(grpc.RpcError) as closed:
        stats(stub, session)
    answers.append((closed.value.code(), closed.value.details().replace(session.session_id, "ID")))
    channel.close()
    return [(code, message.replace(session.session_id, "ID")) for code, message in answers]


def test_refusals_are_those_of_threads(workers: LocalServer, tmp_path: Path) -> None:
    threads = start_local(tmp_path / "threads", "--no-warm-up")
    try:
        expected = refusals(threads.address)
    finally:
        threads.stop()
    assert expected[-1][0] == grpc.StatusCode.NOT_FOUND and expected[len(CASES)][0] == grpc.StatusCode.OK
    assert refusals(workers.address) == expected


def test_a_killed_worker_costs_only_its_session(tmp_path: Path) -> None:
    record_dir = tmp_path / "recordings"
    first = start_local(record_dir, *WORKERS, "--checkpoint-interval", "2")
    try:
        channel, stub = connect(first.address, timeout=60.0)
        doomed, survivor = (SessionRef.from_credentials(stub.CreateSession(create_request(TINY, label)))
                            for label in ("doomed", "survivor"))
        pids = placements(first)
        assert pids[doomed.session_id] != pids[survivor.session_id]

        def kill_after_three(acked: int) -> None:
            if acked == 3:
                os.kill(pids[doomed.session_id], signal.SIGKILL)

        frames = [messages(scene()), messages(scene("20:30"))]
        killed, finished = stream_both(stub, [doomed, survivor], frames, kill_after_three)
        assert finished.error is None and [ack.index for ack in finished.acks] == [f.index for f in frames[1]]
        assert killed.error is not None and killed.error.code() == grpc.StatusCode.UNAVAILABLE
        acked = [ack.index for ack in killed.acks]
        assert 3 <= len(acked) < len(frames[0])
        with pytest.raises(grpc.RpcError) as lost:
            stats(stub, doomed)
        assert lost.value.code() == grpc.StatusCode.UNAVAILABLE
        assert "killed by SIGKILL" in lost.value.details() and "--resume" in lost.value.details()
        health = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(service=""))
        assert health.status == health_pb2.HealthCheckResponse.SERVING
        assert stats(stub, survivor).frames == len(frames[1])
        assert [item.session_id for item in stub.ListSessions(pb.ListSessionsRequest()).sessions] == \
            [survivor.session_id]
        fresh = SessionRef.from_credentials(stub.CreateSession(create_request(FROZEN, "after")))  # on the live one
        assert placements(first)[fresh.session_id] == pids[survivor.session_id]
        channel.close()
    finally:
        first.stop()

    second = start_local(record_dir, *WORKERS)
    try:
        channel, stub = connect(second.address, timeout=60.0)
        standing = stats(stub, doomed)  # the same id and token, back in a worker
        assert standing.last_sequence >= len(acked), "an acknowledged frame was lost"
        assert doomed.session_id in placements(second)
        recorded = recording.load(record_dir / f"{doomed.session_id}.mcap")
        assert [frame.index for _, frame in recorded.frames][:len(acked)] == acked
        stub.CloseSession(pb.CloseSessionRequest(session_id=doomed.session_id), metadata=doomed.metadata())
        channel.close()
        workers_left = {int(pid) for pid in SERVING.findall(second.log_path.read_text())}
        assert len(workers_left) == 2
        second.kill()  # a server killed outright takes its workers with it
        deadline = time.monotonic() + 30
        while any(Path(f"/proc/{pid}").exists() for pid in workers_left) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not any(Path(f"/proc/{pid}").exists() for pid in workers_left), "a worker outlived its server"
    finally:
        second.stop()


def test_limits_count_every_worker_and_idle_sessions_expire(tmp_path: Path) -> None:
    server = start_local(tmp_path / "limits", *WORKERS, "--max-sessions", "2", "--session-idle-seconds", "4")
    try:
        channel, stub = connect(server.address, timeout=60.0)
        idle, busy = (SessionRef.from_credentials(stub.CreateSession(create_request(FROZEN, label)))
                      for label in ("idle", "busy"))
        with pytest.raises(grpc.RpcError) as full:
            stub.CreateSession(create_request(FROZEN, "one too many"))
        assert (full.value.code(), full.value.details()) == (grpc.StatusCode.RESOURCE_EXHAUSTED,
                                                             "the server already holds its limit of 2 sessions")
        deadline = time.monotonic() + 40
        while time.monotonic() < deadline:
            stats(stub, busy)  # in use: it stays
            listed = {item.session_id for item in stub.ListSessions(pb.ListSessionsRequest()).sessions}
            if idle.session_id not in listed:
                break
            time.sleep(0.2)
        assert listed == {busy.session_id}
        with pytest.raises(grpc.RpcError) as expired:
            stats(stub, idle)
        assert expired.value.code() == grpc.StatusCode.NOT_FOUND
        assert recording.load(server.record_dir / f"{idle.session_id}.mcap").stats is not None  # closed cleanly
        again = SessionRef.from_credentials(stub.CreateSession(create_request(FROZEN, "again")))
        placed = placements(server)
        assert placed[again.session_id] == placed[idle.session_id]  # the worker the expired session left
        channel.close()
    finally:
        server.stop()


def test_callers_and_their_quota_hold_across_workers(tmp_path: Path) -> None:
    keys = tmp_path / "keys.txt"
    keys.write_text(f"alice:{digest('alice-key')}\nbob:{digest('bob-key')}\n")
    server = start_local(tmp_path / "callers", *WORKERS, "--api-keys-file", str(keys), "--max-sessions-per-client", "2")
    try:
        channel, stub = connect(server.address, timeout=60.0)
        alice, bob = ((API_KEY_METADATA_KEY, "alice-key"),), ((API_KEY_METADATA_KEY, "bob-key"),)
        with pytest.raises(grpc.RpcError) as anonymous:
            stub.CreateSession(create_request(FROZEN))
        assert anonymous.value.code() == grpc.StatusCode.UNAUTHENTICATED
        hers = [SessionRef.from_credentials(stub.CreateSession(create_request(FROZEN), metadata=alice))
                for _ in range(2)]
        assert len({placements(server)[session.session_id] for session in hers}) == 2  # one on each worker
        with pytest.raises(grpc.RpcError) as over:
            stub.CreateSession(create_request(FROZEN), metadata=alice)
        assert over.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        assert over.value.details() == "the caller key:alice already holds its limit of 2 sessions"
        his = SessionRef.from_credentials(stub.CreateSession(create_request(FROZEN), metadata=bob))
        listed = {item.session_id for item in stub.ListSessions(pb.ListSessionsRequest(), metadata=alice).sessions}
        assert listed == {session.session_id for session in hers}
        assert [item.session_id for item in stub.ListSessions(pb.ListSessionsRequest(), metadata=bob).sessions] == \
            [his.session_id]
        with pytest.raises(grpc.RpcError) as foreign:  # a session answers only to its own token
            stub.GetStats(pb.GetStatsRequest(session_id=hers[0].session_id), metadata=his.metadata())
        assert foreign.value.code() == grpc.StatusCode.UNAUTHENTICATED
        channel.close()
    finally:
        server.stop()
