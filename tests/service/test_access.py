"""Who may call and how much, against servers built in this process with the settings each test needs:
RestoreSession, idle sessions and streams, ListSessions and labels, wrong tokens, API keys, per-caller
quotas, the concurrent-call limit and the metrics endpoint."""

from __future__ import annotations

import threading
import time
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import grpc
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from ogapi import SERVICE_NAME, recording
from ogapi.v1 import mapping_pb2 as pb
from ogapi.v1 import mapping_pb2_grpc as pb_grpc
from ogclient.__main__ import main as ogclient_main
from ogclient.connection import SessionRef, Transport, connect
from ogserver import apikeys

from .bad_frames import broken
from .inprocess import Running, serving, settings
from .scene import FROZEN, PRESET, create_request, messages, scene

CODE = grpc.StatusCode
KEYS = {"alice": "alice's key", "bob": "bob's key"}


def refusal(call, *args, **kwargs) -> grpc.RpcError:
    with pytest.raises(grpc.RpcError) as raised:
        call(*args, **kwargs)
    return raised.value


def held_open(release: threading.Event, *first: pb.RestoreChunk) -> Iterator[pb.RestoreChunk]:
    """A client stream that sends ``first``, then nothing until ``release`` is set."""
    yield from first
    release.wait()


def refused_restore(stub: pb_grpc.MappingStub, *first: pb.RestoreChunk) -> grpc.RpcError:
    """A RestoreSession that sends ``first`` and then waits: the refusal must come before it sends more."""
    release = threading.Event()
    try:
        return refusal(stub.RestoreSession, held_open(release, *first), timeout=10)
    finally:
        release.set()


@contextmanager
def idle_restores(running: Running, count: int) -> Iterator[list[grpc.Future]]:
    """``count`` RestoreSession calls that send nothing until the block ends, given time to reach the server."""
    release = threading.Event()
    calls = [running.stub.RestoreSession.future(held_open(release)) for _ in range(count)]
    try:
        time.sleep(1.0)
        yield calls
    finally:
        release.set()
        for call in calls:
            call.cancel()


def health_check(address: str, timeout: float) -> int:
    with grpc.insecure_channel(address) as channel:
        request = health_pb2.HealthCheckRequest(service=SERVICE_NAME)
        return health_pb2_grpc.HealthStub(channel).Check(request, timeout=timeout).status


def as_caller(running: Running, name: str):
    channel, stub = connect(running.address, 10, Transport(api_key=KEYS[name]))
    return channel, stub


@pytest.fixture
def keyed(tmp_path: Path) -> Iterator[Running]:
    """API keys for alice and bob, one session each at most."""
    configured = settings(tmp_path)
    configured.access.api_keys = {name: apikeys.digest(key) for name, key in KEYS.items()}
    configured.access.max_sessions_per_client = 1
    with serving(configured) as running:
        yield running


# ---------------------------------------------------------------------------- RestoreSession


def test_idle_restores_leave_the_health_check_answering(tmp_path: Path) -> None:
    """24 RestoreSession calls that send nothing: before, they took every worker thread."""
    configured = settings(tmp_path)
    configured.limits.max_sessions = 6
    with serving(configured) as running, idle_restores(running, 24) as calls:
        start = time.monotonic()
        assert health_check(running.address, timeout=1.0) == health_pb2.HealthCheckResponse.SERVING
        assert time.monotonic() - start < 1.0
        refused = [call for call in calls if call.done()]  # those over the session limit, at once
        assert len(refused) == 18 and all(call.code() == CODE.RESOURCE_EXHAUSTED for call in refused)


def test_a_full_server_refuses_a_restore_at_its_first_chunk(tmp_path: Path) -> None:
    configured = settings(tmp_path)
    configured.limits.max_sessions = 1
    with serving(configured) as running:
        running.stub.CreateSession(create_request(FROZEN))
        error = refused_restore(running.stub, pb.RestoreChunk(data=b"0" * 1000))
        assert error.code() == CODE.RESOURCE_EXHAUSTED and "limit of 1 sessions" in error.details()


def test_restore_needs_an_api_key_before_any_chunk(keyed: Running) -> None:
    error = refused_restore(keyed.stub)
    assert error.code() == CODE.UNAUTHENTICATED and error.details() == "x-api-key: metadata is missing"


def test_a_stalled_restore_is_ended(tmp_path: Path) -> None:
    configured = settings(tmp_path)
    configured.access.restore_idle_seconds = 0.5
    with serving(configured) as running:
        error = refused_restore(running.stub, pb.RestoreChunk(data=b"0"))
        assert error.code() == CODE.DEADLINE_EXCEEDED and "restore_idle_seconds" in error.details()
        running.stub.CreateSession(create_request(FROZEN))  # its reservation was given back


def test_mapping_calls_beyond_the_limit_are_refused_and_health_still_answers(tmp_path: Path) -> None:
    configured = settings(tmp_path)
    configured.access.max_concurrent_calls = 2
    with serving(configured) as running, idle_restores(running, 2):
        error = refusal(running.stub.ListSessions, pb.ListSessionsRequest(), timeout=5)
        assert error.code() == CODE.RESOURCE_EXHAUSTED and "limit of 2 concurrent calls" in error.details()
        assert health_check(running.address, timeout=1.0) == health_pb2.HealthCheckResponse.SERVING


# ---------------------------------------------------------------------------- idle sessions and streams


def test_an_unused_session_expires_and_its_recording_is_finished(tmp_path: Path) -> None:
    configured = settings(tmp_path)
    configured.access.session_idle_seconds = 0.5
    with serving(configured) as running:
        credentials = running.stub.CreateSession(create_request(FROZEN))
        busy = SessionRef.from_credentials(running.stub.CreateSession(create_request(FROZEN)))
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            running.stub.GetStats(pb.GetStatsRequest(session_id=busy.session_id), metadata=busy.metadata())
            listed = {info.session_id for info in running.stub.ListSessions(pb.ListSessionsRequest()).sessions}
            if credentials.session_id not in listed:
                break
            time.sleep(0.1)
        assert listed == {busy.session_id}  # the session in use stays
        error = refusal(running.stub.GetStats, pb.GetStatsRequest(session_id=credentials.session_id),
                        metadata=SessionRef.from_credentials(credentials).metadata())
        assert error.code() == CODE.NOT_FOUND
        recorded = Path(configured.record_dir) / credentials.recording
        assert recording.load(recorded).stats is not None  # closed like CloseSession


def test_a_stalled_stream_is_ended_and_frees_the_sessions_stream(tmp_path: Path) -> None:
    configured = settings(tmp_path)
    configured.access.stream_idle_seconds = 1.0
    frames = messages(scene("0:3"))
    with serving(configured) as running:
        session = SessionRef.from_credentials(running.stub.CreateSession(create_request(FROZEN)))
        release = threading.Event()

        def stalled() -> Iterator[pb.Frame]:
            yield frames[0]
            release.wait()

        try:
            error = refusal(lambda: list(running.stub.StreamFrames(stalled(), metadata=session.stream_metadata(),
                                                                   timeout=15)))
        finally:
            release.set()
        assert error.code() == CODE.DEADLINE_EXCEEDED and "stream_idle_seconds" in error.details()
        acks = list(running.stub.StreamFrames(iter(frames[1:]), metadata=session.stream_metadata(), timeout=60))
        assert [ack.accepted for ack in acks] == [True, True]


def test_queued_frames_are_held_to_a_byte_budget(tmp_path: Path) -> None:
    """Queued frames once had no byte budget: a session could hold any amount of memory."""
    configured = settings(tmp_path)
    configured.limits.max_queued_bytes = 1  # smaller than any frame: one frame in the session at a time
    frames = messages(scene("0:4"))
    with serving(configured) as running:
        session = SessionRef.from_credentials(running.stub.CreateSession(create_request(FROZEN)))
        acks = list(running.stub.StreamFrames(iter(frames), metadata=session.stream_metadata(), timeout=60))
    assert all(ack.accepted for ack in acks)
    assert [ack.queue_depth for ack in acks] == [0] * len(frames)  # nothing waited behind a frame being mapped


# ---------------------------------------------------------------------------- ListSessions and labels


def test_create_and_close_name_files_in_the_record_dir_not_server_paths(tmp_path: Path) -> None:
    configured = settings(tmp_path)
    configured.final_snapshots = True
    with serving(configured) as running:
        credentials = running.stub.CreateSession(create_request(FROZEN))
        session = SessionRef.from_credentials(credentials)
        assert credentials.recording == f"{session.session_id}.mcap"
        closed = running.stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id),
                                           metadata=session.metadata())
    assert (closed.recording, closed.snapshot) == (f"{session.session_id}.mcap", f"{session.session_id}.safetensors")
    record_dir = Path(configured.record_dir)
    assert (record_dir / closed.recording).is_file() and (record_dir / closed.snapshot).is_file()


def test_ogclient_names_the_files_in_the_servers_record_dir(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    session_file = str(tmp_path / "session.json")
    configured = settings(tmp_path)
    with serving(configured) as running:
        assert ogclient_main(["--server", running.address, "create", "--preset", PRESET,
                              "--session-out", session_file]) == 0
        assert ogclient_main(["--server", running.address, "close", "--session", session_file]) == 0
    session_id = SessionRef.load(session_file).session_id
    printed = capsys.readouterr().out
    assert f"server records to {session_id}.mcap in its record dir" in printed
    assert f"recording {session_id}.mcap in the server's record dir" in printed
    assert configured.record_dir not in printed


def test_listing_shows_no_server_paths_and_long_labels_are_refused(tmp_path: Path) -> None:
    with serving(settings(tmp_path)) as running:
        running.stub.CreateSession(create_request(FROZEN, "short"))
        (info,) = running.stub.ListSessions(pb.ListSessionsRequest()).sessions
        assert info.recording == f"{info.session_id}.mcap"
        error = refusal(running.stub.CreateSession, create_request(FROZEN, "x" * 257))
        assert error.code() == CODE.INVALID_ARGUMENT and error.details().startswith("label: longer than")
        chunk = pb.RestoreChunk(data=b"0", label="x" * 257)
        error = refusal(running.stub.RestoreSession, iter([chunk]))
        assert error.code() == CODE.INVALID_ARGUMENT and error.details().startswith("label: longer than")


def test_callers_see_only_their_own_sessions_within_their_quota(keyed: Running) -> None:
    alice_channel, alice = as_caller(keyed, "alice")
    bob_channel, bob = as_caller(keyed, "bob")
    with alice_channel, bob_channel:
        mine = alice.CreateSession(create_request(FROZEN, "alice's")).session_id
        error = refusal(alice.CreateSession, create_request(FROZEN))
        assert error.code() == CODE.RESOURCE_EXHAUSTED and "key:alice already holds its limit of 1" in error.details()
        theirs = bob.CreateSession(create_request(FROZEN, "bob's")).session_id
        assert [info.session_id for info in alice.ListSessions(pb.ListSessionsRequest()).sessions] == [mine]
        assert [info.session_id for info in bob.ListSessions(pb.ListSessionsRequest()).sessions] == [theirs]
    for call, request in ((keyed.stub.ListSessions, pb.ListSessionsRequest()),
                          (keyed.stub.CreateSession, create_request(FROZEN))):
        assert refusal(call, request).code() == CODE.UNAUTHENTICATED
    error = refusal(keyed.stub.ListSessions, pb.ListSessionsRequest(), metadata=(("x-api-key", "guess"),))
    assert error.code() == CODE.UNAUTHENTICATED and error.details() == "x-api-key: not a key this server accepts"


def test_ogclient_sends_the_api_key(keyed: Running, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    key_file = tmp_path / "alice.key"
    key_file.write_text(KEYS["alice"] + "\n")
    session_file = str(tmp_path / "session.json")
    assert ogclient_main(["--server", keyed.address, "--api-key-file", str(key_file), "create", "--preset", PRESET,
                          "--label", "from the CLI", "--session-out", session_file]) == 0
    monkeypatch.setenv("OGMAP_API_KEY", KEYS["alice"])
    assert ogclient_main(["--server", keyed.address, "list"]) == 0
    assert "label='from the CLI'" in capsys.readouterr().out
    monkeypatch.setenv("OGMAP_API_KEY", KEYS["bob"])
    assert ogclient_main(["--server", keyed.address, "list"]) == 0
    assert capsys.readouterr().out.strip() == "no sessions"


# ---------------------------------------------------------------------------- wrong tokens


def test_failures_from_an_address_never_refuse_right_credentials_from_it(keyed: Running,
                                                                        caplog: pytest.LogCaptureFixture) -> None:
    """A client sends 25 wrong tokens and 25 wrong keys from 127.0.0.1 (past the limit of 20); other clients
    at the same address (as behind one NAT) still create, list, stream and close with their key and token."""
    alice_channel, alice = as_caller(keyed, "alice")
    bob_channel, bob = as_caller(keyed, "bob")
    with alice_channel, bob_channel:
        session = SessionRef.from_credentials(alice.CreateSession(create_request(FROZEN)))
        request = pb.GetStatsRequest(session_id=session.session_id)
        wrong_token = SessionRef(session.session_id, "guess").metadata()
        codes = [refusal(keyed.stub.GetStats, request, metadata=wrong_token).code() for _ in range(25)]
        codes += [refusal(keyed.stub.ListSessions, pb.ListSessionsRequest(), metadata=(("x-api-key", f"guess {n}"),)
                          ).code() for n in range(25)]
        assert codes == [CODE.UNAUTHENTICATED] * 20 + [CODE.RESOURCE_EXHAUSTED] * 30
        assert alice.GetStats(request, metadata=session.metadata()).session_id == session.session_id
        assert [info.session_id for info in alice.ListSessions(pb.ListSessionsRequest()).sessions] == \
            [session.session_id]
        acks = list(alice.StreamFrames(iter(messages(scene("0:1"))), metadata=session.stream_metadata(), timeout=300))
        assert [ack.accepted for ack in acks] == [True]
        other = SessionRef.from_credentials(bob.CreateSession(create_request(FROZEN)))
        bob.CloseSession(pb.CloseSessionRequest(session_id=other.session_id), metadata=other.metadata())
        error = refusal(keyed.stub.GetStats, request, metadata=wrong_token)
        assert error.code() == CODE.RESOURCE_EXHAUSTED
        assert error.details() == ("too many failed authentications from 127.0.0.1 (20 in 60 s); "
                                   "x-session-token: does not match the session")
    warnings = [record.getMessage() for record in caplog.records if "authentication failed" in record.getMessage()]
    assert 1 <= len(warnings) <= 3 and "127.0.0.1" in warnings[0]


# ---------------------------------------------------------------------------- metrics


def test_metrics_are_scraped(tmp_path: Path) -> None:
    configured = settings(tmp_path)
    configured.access.metrics_address = "127.0.0.1:0"
    frames = messages(scene("0:3"))
    bad = broken(frames[0], lambda message: message.ClearField("c2w"))
    with serving(configured) as running:
        session = SessionRef.from_credentials(running.stub.CreateSession(create_request(FROZEN)))
        acks = list(running.stub.StreamFrames(iter([*frames, bad]), metadata=session.stream_metadata(), timeout=60))
        assert [ack.accepted for ack in acks].count(True) == 3
        with urllib.request.urlopen(f"http://127.0.0.1:{running.server.metrics.port}/metrics", timeout=5) as page:
            text = page.read().decode()
    for line in ("ogserver_sessions 1.0", 'ogserver_frames_total{outcome="accepted"} 3.0',
                 'ogserver_frames_total{outcome="rejected"} 1.0', 'ogserver_frames_total{outcome="mapped"} 3.0',
                 'ogserver_frames_total{outcome="skipped"} 0.0', "ogserver_ack_latency_seconds_count 3.0",
                 'ogserver_frame_refusals_total{code="INVALID_ARGUMENT"} 1.0',
                 'ogserver_calls_total{code="OK",method="CreateSession"} 1.0',
                 f'ogserver_session_queue_depth{{session_id="{session.session_id}"}} 0.0'):
        assert line in text, line
    assert f'ogserver_session_mapping_fps{{session_id="{session.session_id}"}}' in text
