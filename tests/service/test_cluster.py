"""Cluster mode end to end on a real two-node Ray cluster with two front-ends (``ogserver --cluster``).

Two sessions, one CPU each on nodes of one CPU each (so each on its own node), stream the tiny
synthetic scene at the same time, one through each front-end; every call on a session is then made
through the other front-end: renders match a local copy of the map, stats and listings agree, limits
hold cluster-wide and refusals carry the single server's codes.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc
import numpy as np
import pytest
from google.protobuf.message import Message
from ogapi.v1 import mapping_pb2 as pb
from ogapi.v1 import mapping_pb2_grpc as pb_grpc
from ogclient.connection import SessionRef, connect
from ogclient.evaluation import render, snapshot_bytes
from ogclient.local_server import LocalServer
from ogclient.streaming import StreamResult, stream_frames
from ogserver.cluster.local import local_cluster

from ogmapping.mapper import Mapper
from ogmapping.metrics import psnr

from .scene import TEST_SERVER_CONFIG, TINY, create_request, messages, scene

pytest.importorskip("ray", reason="cluster mode needs Ray: the 'cluster' extra (make cluster-test installs it)")

pytestmark = pytest.mark.cluster


@dataclass
class FrontEnd:
    local: LocalServer
    channel: grpc.Channel
    stub: pb_grpc.MappingStub

    def call(self, method: str, request: Message, session: SessionRef) -> Any:
        return getattr(self.stub, method)(request, metadata=session.metadata())


@dataclass
class Cluster:
    address: str
    front_ends: list[FrontEnd]


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    """Two front-ends of one two-node cluster, sharing one record dir (the storage every node sees)."""
    record_dir = tmp_path_factory.mktemp("recordings")
    logs = tmp_path_factory.mktemp("logs")
    started: list[FrontEnd] = []
    with local_cluster(logs, nodes=2, cpus_per_node=1) as address:
        try:
            for number in range(2):
                local = LocalServer(record_dir, "--config", str(TEST_SERVER_CONFIG), "--device", "cpu", "--cluster",
                                    address, "--max-sessions", "2", log_path=logs / f"front-end{number}.log")
                local.start()
                started.append(FrontEnd(local, *connect(local.address, timeout=60.0)))
            yield Cluster(address, started)
        finally:
            for front_end in started:
                front_end.channel.close()
                front_end.local.stop()


def stream(front_end: FrontEnd, session: SessionRef, frames: list[pb.Frame], results: dict[str, StreamResult]) -> None:
    results[session.session_id] = stream_frames(front_end.stub, session, frames, progress=False)


def test_any_front_end_serves_any_session(cluster: Cluster) -> None:
    front_ends = cluster.front_ends
    a, b = front_ends
    frames = scene()
    sent = messages(frames)
    sessions = [SessionRef.from_credentials(a.stub.CreateSession(create_request(TINY, f"robot{n}"))) for n in range(2)]
    with pytest.raises(grpc.RpcError) as full:
        b.stub.CreateSession(create_request(TINY, "third"))
    assert full.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED and "cluster" in full.value.details()

    results: dict[str, StreamResult] = {}
    threads = [threading.Thread(target=stream, args=(front_end, session, sent, results))
               for front_end, session in zip(front_ends, sessions, strict=True)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    for session in sessions:
        acks = results[session.session_id].acks
        assert [ack.index for ack in acks] == frames.selection.streamed
        assert [ack.sequence for ack in acks] == list(range(1, len(sent) + 1))
        assert all(ack.accepted and ack.anchors > 0 for ack in acks)

    first = sessions[0]
    stats = b.call("GetStats", pb.GetStatsRequest(session_id=first.session_id), first)
    assert stats.frames == stats.frames_received == len(sent) and stats.queue_depth == 0
    listed = {info.session_id for info in b.stub.ListSessions(pb.ListSessionsRequest()).sessions}
    assert listed == {session.session_id for session in sessions}

    local = Mapper.restore(snapshot_bytes(b.stub, first), "cpu")
    for position in (frames.selection.streamed[-1], frames.selection.heldout[0]):
        frame = frames.load(position)
        through_b = render(b.stub, first, frame.c2w, frame.color_intrinsics)
        through_a = render(a.stub, first, frame.c2w, frame.color_intrinsics)
        mine = local.render(frame.c2w, frame.color_intrinsics)
        assert through_b.color.std() > 0.01 and psnr(through_b.color, mine.color) > 40.0
        np.testing.assert_array_equal(through_a.color, through_b.color)

    wrong = SessionRef(first.session_id, "not-the-token")
    for front_end, session, code in ((a, wrong, grpc.StatusCode.UNAUTHENTICATED),
                                     (b, SessionRef("0" * 32, first.token), grpc.StatusCode.NOT_FOUND)):
        with pytest.raises(grpc.RpcError) as refused:
            front_end.call("GetStats", pb.GetStatsRequest(session_id=session.session_id), session)
        assert refused.value.code() == code

    for front_end, session in zip(front_ends, sessions, strict=True):
        closed = front_end.call("CloseSession", pb.CloseSessionRequest(session_id=session.session_id), session)
        assert closed.stats.frames == len(sent) and Path(closed.recording).stat().st_size > 0
    with pytest.raises(grpc.RpcError) as gone:
        b.call("GetStats", pb.GetStatsRequest(session_id=first.session_id), first)
    assert gone.value.code() == grpc.StatusCode.NOT_FOUND
    assert not b.stub.ListSessions(pb.ListSessionsRequest()).sessions


def wait_for_stats(front_end: FrontEnd, session: SessionRef, frames: int) -> pb.Stats:
    """The session's stats once it answers again and has mapped ``frames`` frames (UNAVAILABLE meanwhile)."""
    deadline = time.monotonic() + 180.0
    while True:
        try:
            stats = front_end.call("GetStats", pb.GetStatsRequest(session_id=session.session_id), session)
            if stats.frames >= frames and stats.queue_depth == 0:
                return stats
        except grpc.RpcError as error:
            assert error.code() == grpc.StatusCode.UNAVAILABLE, error.details()
        assert time.monotonic() < deadline, "the session did not come back"
        time.sleep(0.5)


def test_a_session_whose_actor_dies_comes_back_with_its_id_token_and_frames(cluster: Cluster) -> None:
    import ray
    from ogserver.cluster.host import NAMESPACE, actor_name

    a, b = cluster.front_ends
    frames = scene()
    sent = messages(frames)
    session = SessionRef.from_credentials(a.stub.CreateSession(create_request(TINY, "crashing")))
    acks = stream_frames(a.stub, session, sent[:6], progress=False).acks
    assert [ack.sequence for ack in acks] == list(range(1, 7)) and all(ack.accepted for ack in acks)
    frame = frames.load(frames.selection.heldout[0])
    before = render(b.stub, session, frame.c2w, frame.color_intrinsics)

    killed = time.monotonic()
    ray.init(address=cluster.address, namespace=NAMESPACE, log_to_driver=False)
    try:  # as if its worker process crashed: Ray restarts it, on any node with a free CPU
        ray.kill(ray.get_actor(actor_name(session.session_id)), no_restart=False)
    finally:
        ray.shutdown()
    stats = wait_for_stats(b, session, 6)  # the old token, through the other front-end
    assert stats.session_id == session.session_id and stats.last_sequence == 6
    assert stats.uptime_seconds < time.monotonic() - killed  # a new actor, resumed from the checkpoint
    after = render(b.stub, session, frame.c2w, frame.color_intrinsics)
    assert psnr(after.color, before.color) > 40.0 and np.abs(after.depth - before.depth).mean() < 0.01

    more = stream_frames(a.stub, session, sent[6:], progress=False).acks
    assert [ack.sequence for ack in more] == list(range(7, len(sent) + 1)) and all(ack.accepted for ack in more)
    closed = b.call("CloseSession", pb.CloseSessionRequest(session_id=session.session_id), session)
    assert closed.stats.frames_received == len(sent)
