"""Cluster mode end to end on a real Ray cluster with two front-ends (``ogserver --cluster``).

A head node that takes no session (0 CPUs) and two worker nodes of two CPUs each; sessions ask for one
CPU and are spread over nodes (SPREAD). Two sessions stream the tiny synthetic scene at the same time,
one through each front-end; every call on a session is then made through the other front-end: renders
match a local copy of the map, stats and listings agree, limits hold cluster-wide and refusals carry
the single server's codes. Then the node holding one session is killed mid-stream (its whole
``ray start`` process group, SIGKILL): that stream ends UNAVAILABLE, the other session's stream goes
on, the session comes back on the surviving node with its id, token and every acknowledged frame,
takes the rest of the frames and renders what a single server's map of the same frames renders.
Last, a session whose actor is dead for good gives its place in the cluster back.
"""

from __future__ import annotations

import re
import threading
import time
from collections.abc import Iterable, Iterator
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
from ogclient.resuming import stream_resuming
from ogclient.streaming import StreamResult, stream_frames
from ogserver.cluster.local import LocalCluster, local_cluster

from ogmapping.mapper import Mapper
from ogmapping.quality.metrics import psnr

from .inprocess import serving, settings
from .scene import TEST_SERVER_CONFIG, TINY, create_request, messages, scene

ray = pytest.importorskip("ray", reason="cluster mode needs Ray: the 'cluster' extra (make cluster-test installs it)")

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
    local: LocalCluster
    front_ends: list[FrontEnd]
    shared: Path  # the shared storage's folder (its URL is file://...)

    def node_of(self, session: SessionRef) -> str:
        """The Ray node id of the node the session's actor runs on now."""
        from ogserver.cluster.host import actor_name

        return ray.get(ray.get_actor(actor_name(session.session_id)).node_id.remote(), timeout=120.0)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    """Two front-ends of one cluster (a head and two worker nodes); recordings and checkpoints at a file:// URL
    through fsspec, as on s3:// (the record dir is then scratch space); this process is a Ray driver too, to
    find and kill nodes and actors."""
    from ogserver.cluster.host import NAMESPACE

    record_dir = tmp_path_factory.mktemp("recordings")
    logs = tmp_path_factory.mktemp("logs")
    started: list[FrontEnd] = []
    with local_cluster(logs, workers=2, cpus_per_node=2, head_cpus=0, fast_failure_detection=True) as local:
        try:
            for number in range(2):
                front_end = LocalServer(record_dir, "--config", str(TEST_SERVER_CONFIG), "--device", "cpu",
                                        "--cluster", local.address, "--max-sessions", "2", "--checkpoint-interval",
                                        "2", "--shared-storage", (record_dir / "shared").as_uri(),
                                        log_path=logs / f"front-end{number}.log")
                front_end.start()
                started.append(FrontEnd(front_end, *connect(front_end.address, timeout=60.0)))
            ray.init(address=local.address, namespace=NAMESPACE, log_to_driver=False)
            yield Cluster(local, started, record_dir / "shared")
        finally:
            ray.shutdown()
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
        assert closed.stats.frames == len(sent) and closed.recording == f"{session.session_id}.mcap"
        assert cluster.shared.joinpath(f"{session.session_id}.mcap").stat().st_size > 0  # published
    with pytest.raises(grpc.RpcError) as gone:
        b.call("GetStats", pb.GetStatsRequest(session_id=first.session_id), first)
    assert gone.value.code() == grpc.StatusCode.NOT_FOUND
    assert not b.stub.ListSessions(pb.ListSessionsRequest()).sessions


def wait_for_stats(front_end: FrontEnd, session: SessionRef, mapped: int | None = None) -> pb.Stats:
    """The session's stats once it answers (UNAVAILABLE while Ray restarts it) with ``mapped`` frames mapped, or,
    by default, nothing left to map."""
    deadline = time.monotonic() + 120.0
    while True:
        try:
            stats = front_end.call("GetStats", pb.GetStatsRequest(session_id=session.session_id), session)
            if (stats.mapped_sequence >= mapped if mapped is not None else
                    stats.queue_depth == 0 and stats.mapped_sequence == stats.last_sequence):
                return stats
        except grpc.RpcError as error:
            assert error.code() == grpc.StatusCode.UNAVAILABLE, error.details()
        assert time.monotonic() < deadline, "the session did not come back"
        time.sleep(0.2)


@dataclass
class Cut:
    acks: list[pb.FrameAck]
    error: grpc.RpcError | None = None


def held_back(frames: list[pb.Frame], first: int, release: threading.Event) -> Iterator[pb.Frame]:
    """``first`` frames, then the others once ``release`` is set: the stream is still open when its node goes."""
    for number, frame in enumerate(frames):
        if number == first:
            assert release.wait(120.0)
        yield frame


def stream_until_cut(front_end: FrontEnd, session: SessionRef, frames: Iterable[pb.Frame], acked: threading.Event,
                     after: int, cut: Cut) -> None:
    """Stream ``frames``, setting ``acked`` once ``after`` are acknowledged, until the stream ends."""
    try:
        for ack in front_end.stub.StreamFrames(iter(frames), metadata=session.stream_metadata()):
            cut.acks.append(ack)
            if len(cut.acks) == after:
                acked.set()
    except grpc.RpcError as error:
        cut.error = error
    finally:
        acked.set()


def single_server_render(tmp_path: Path, frames: list[pb.Frame], position: int) -> tuple[np.ndarray, np.ndarray]:
    """What an ogserver of its own (in this process) renders from ``position`` after mapping ``frames``."""
    frame = scene().load(position)
    with serving(settings(tmp_path)) as server:
        session = SessionRef.from_credentials(server.stub.CreateSession(create_request(TINY, "single")))
        acks = stream_frames(server.stub, session, frames, progress=False).acks
        assert all(ack.accepted for ack in acks) and len(acks) == len(frames)
        rendered = render(server.stub, session, frame.c2w, frame.color_intrinsics)
    return rendered.color, rendered.depth


KILL_AFTER = 4  # frames mapped: two checkpoints written (every 2 frames); two more frames sent, the rest held back
UNAVAILABLE_CUT = ("the frame stream was cut: UNAVAILABLE: the session's Ray actor stopped answering (its process or "
                   "node failed)")


def test_losing_the_node_of_a_session_mid_stream(cluster: Cluster, tmp_path: Path) -> None:
    a, b = cluster.front_ends
    frames = scene()
    sent = messages(frames)
    lost, kept = (SessionRef.from_credentials(a.stub.CreateSession(create_request(TINY, name)))
                  for name in ("lost", "kept"))
    lost_node, kept_node = cluster.node_of(lost), cluster.node_of(kept)
    head = cluster.local.nodes[0]
    assert lost_node != kept_node, "both sessions were placed on one node"
    assert head not in (cluster.local.node_of(lost_node), cluster.local.node_of(kept_node))

    killed, said, cut, whole = threading.Event(), [], Cut([]), Cut([])

    def frames_after(last_index: int | None) -> Iterator[pb.Frame]:
        """What ogclient streams: all frames (the later ones held back until the node is killed), then, after
        a cut, those after the last one the session holds."""
        if last_index is None:
            return held_back(sent, KILL_AFTER + 2, killed)
        return iter([message for message in sent if message.index > last_index])

    def stream_lost() -> None:
        try:
            cut.acks = stream_resuming(a.stub, lost, frames_after, progress=False, say=said.append).acks
        except Exception as error:  # reported by the assertions below
            said.append(f"failed: {error!r}")

    streams = [threading.Thread(target=stream_lost),
               threading.Thread(target=stream_until_cut,
                                args=(a, kept, held_back(sent, KILL_AFTER, killed), threading.Event(), 0, whole))]
    for thread in streams:
        thread.start()
    wait_for_stats(b, lost, mapped=KILL_AFTER)
    cluster.local.node_of(lost_node).kill()
    killed.set()
    for thread in streams:
        thread.join(300.0)
    assert whole.error is None and [ack.sequence for ack in whole.acks] == list(range(1, len(sent) + 1))

    # ogclient saw the stream end UNAVAILABLE, waited for the session, asked GetStats and went on after it
    assert sum(UNAVAILABLE_CUT in line for line in said) == 1, said
    resuming = [re.fullmatch(r"resuming: the session holds (\d+) frames, the last with index (\d+); streaming "
                             r"the frames after it", line) for line in said if line.startswith("resuming")]
    assert len(resuming) == 1 and resuming[0], said
    held, last_index = int(resuming[0][1]), int(resuming[0][2])
    assert held >= KILL_AFTER, "a frame mapped before the node was lost is gone"
    sequences = [ack.sequence for ack in cut.acks]
    before = [sequence for sequence in sequences if sequence <= held]
    assert before == list(range(1, len(before) + 1)) and before, "no acknowledged frame may be lost"
    assert sequences == before + list(range(held + 1, len(sent) + 1)), "the resumed stream goes on after it"
    assert all(ack.accepted for ack in cut.acks)
    assert next(ack.index for ack in cut.acks if ack.sequence > held) > last_index

    done = wait_for_stats(b, lost)  # the same id and token, through the other front-end
    assert done.session_id == lost.session_id
    assert done.last_sequence == done.mapped_sequence == len(sent), "each streamed frame is in the map once"
    assert cluster.node_of(lost) == kept_node, "not restarted on the surviving node"
    resumed = re.search(rf"session {lost.session_id} resumed for \S+ from its checkpoint at frame (\d+), (\d+) "
                        "recorded frames after it", cluster.local.worker_logs())
    assert resumed, "the restarted actor did not resume the session from its checkpoint"
    checkpointed, replayed = int(resumed[1]), int(resumed[2])
    assert checkpointed >= 2 and checkpointed + replayed == held

    position = frames.selection.heldout[0]
    frame = frames.load(position)
    after = render(b.stub, lost, frame.c2w, frame.color_intrinsics)
    color, depth = single_server_render(tmp_path, sent, position)
    assert psnr(after.color, color) > 40.0, "the recovered map differs from a single server's"
    assert np.abs(after.depth - depth).mean() < 0.01

    for session in (lost, kept):
        closed = b.call("CloseSession", pb.CloseSessionRequest(session_id=session.session_id), session)
        assert closed.stats.last_sequence == len(sent)


def test_a_session_dead_for_good_gives_its_place_back(cluster: Cluster) -> None:
    from ogserver.cluster.host import actor_name

    a, b = cluster.front_ends
    dead, alive = (SessionRef.from_credentials(a.stub.CreateSession(create_request(TINY, name)))
                   for name in ("dead", "alive"))
    with pytest.raises(grpc.RpcError) as full:
        b.stub.CreateSession(create_request(TINY, "third"))
    assert full.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    ray.kill(ray.get_actor(actor_name(dead.session_id)), no_restart=True)  # as when Ray's restarts are spent
    third = SessionRef.from_credentials(b.stub.CreateSession(create_request(TINY, "third")))
    listed = {info.session_id for info in a.stub.ListSessions(pb.ListSessionsRequest()).sessions}
    assert listed == {alive.session_id, third.session_id}
    with pytest.raises(grpc.RpcError) as gone:
        b.call("GetStats", pb.GetStatsRequest(session_id=dead.session_id), dead)
    assert gone.value.code() == grpc.StatusCode.NOT_FOUND
    for session in (alive, third):
        b.call("CloseSession", pb.CloseSessionRequest(session_id=session.session_id), session)
