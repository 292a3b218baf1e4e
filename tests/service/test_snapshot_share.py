"""A session's GetSnapshot calls are held to ``limits.max_snapshots_per_session`` at once: one tenant's
unread snapshot streams of one session once took every call slot of the server."""

from __future__ import annotations

import threading
from concurrent.futures import ThreadPoolExecutor

import grpc
import pytest
from ogapi.v1 import mapping_pb2 as pb
from ogclient.connection import SessionRef
from ogserver.sessions.session import Session
from ogserver.settings import load

from .inprocess import serving, settings
from .scene import FROZEN, create_request

LIMIT = 2


def test_a_session_runs_at_most_its_share_of_snapshot_calls(tmp_path, monkeypatch) -> None:
    configured = settings(tmp_path)
    configured.limits.max_snapshots_per_session = LIMIT
    inside, release = threading.Semaphore(0), threading.Event()
    original = Session.snapshot

    def held(session: Session) -> bytes:
        if session.config.label == "held":
            inside.release()
            assert release.wait(60)
        return original(session)

    monkeypatch.setattr(Session, "snapshot", held)
    with serving(configured) as running, ThreadPoolExecutor(LIMIT) as pool:
        session, other = (SessionRef.from_credentials(running.stub.CreateSession(create_request(FROZEN, label)))
                          for label in ("held", "free"))

        def snapshot(ref: SessionRef) -> bytes:
            request = pb.GetSnapshotRequest(session_id=ref.session_id)
            return b"".join(chunk.data for chunk in running.stub.GetSnapshot(request, metadata=ref.metadata()))

        running_calls = [pool.submit(snapshot, session) for _ in range(LIMIT)]
        for _ in range(LIMIT):
            assert inside.acquire(timeout=30)
        with pytest.raises(grpc.RpcError) as refused:
            snapshot(session)
        assert refused.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        assert "limits.max_snapshots_per_session" in refused.value.details()
        assert f"{LIMIT} GetSnapshot calls" in refused.value.details()
        assert snapshot(other), "another session's snapshots are served meanwhile"
        release.set()
        assert all(call.result(30) for call in running_calls)
        assert snapshot(session), "the calls ended: the session's share is free again"


def test_the_share_is_a_setting_of_at_least_one() -> None:
    assert load(flags={"max_snapshots_per_session": 3}).limits.max_snapshots_per_session == 3
    with pytest.raises(ValueError, match=r"limits\.max_snapshots_per_session"):
        load(flags={"max_snapshots_per_session": 0})
