"""The access pieces on their own: paced client streams, failed-authentication limits, API keys and
caller identities, the queued-bytes budget, the access settings and keepalive."""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Iterator

import grpc
import pytest
from ogserver import apikeys
from ogserver.access.callers import ANONYMOUS, Callers
from ogserver.access.failed_auth import FailedAuthentications, peer_address
from ogserver.access.transport import keepalive_options
from ogserver.api.pacing import Paced, Timeout
from ogserver.errors import ServiceError
from ogserver.sessions.queued_bytes import ByteBudget
from ogserver.settings import Access, load

# ---------------------------------------------------------------------------- paced streams


def trickle(items: list[int], pause: float, then_block: threading.Event | None = None) -> Iterator[int]:
    for item in items:
        time.sleep(pause)
        yield item
    if then_block is not None:
        then_block.wait()


def test_paced_passes_every_message_through() -> None:
    assert list(Paced(iter([1, 2, 3]), Timeout(5, "idle"), Timeout(5, "total"))) == [1, 2, 3]


def test_paced_refuses_a_client_that_stops_sending() -> None:
    release = threading.Event()
    paced = Paced(trickle([1], 0.0, release), Timeout(0.3, "stream_idle_seconds"))
    try:
        assert next(paced) == 1
        start = time.monotonic()
        with pytest.raises(ServiceError) as refusal:
            next(paced)
        assert 0.25 < time.monotonic() - start < 2.0
        assert refusal.value.code == grpc.StatusCode.DEADLINE_EXCEEDED
        assert "sent nothing for 0.3 s (the server's stream_idle_seconds)" in refusal.value.message
        with pytest.raises(StopIteration):
            next(paced)
    finally:
        release.set()


def test_paced_refuses_a_call_over_its_total_time() -> None:
    paced = Paced(trickle(list(range(100)), 0.1), Timeout(1.0, "restore_idle_seconds"),
                  Timeout(0.5, "restore_seconds"))
    with pytest.raises(ServiceError) as refusal:
        list(paced)
    assert "did not finish within 0.5 s (the server's restore_seconds)" in refusal.value.message


def test_paced_reads_only_when_asked() -> None:
    """Backpressure: the client's next message is not read before the server asks for it."""
    read: list[int] = []

    def counted() -> Iterator[int]:
        for item in range(10):
            read.append(item)
            yield item

    paced = Paced(counted(), Timeout(5, "idle"))
    assert next(paced) == 0
    time.sleep(0.2)
    assert read == [0]


def test_a_paced_stream_closed_early_lets_its_helper_go() -> None:
    paced = Paced(iter(range(10)), Timeout(5, "idle"))
    assert next(paced) == 0
    paced.close()
    paced._helper.join(2)
    assert not paced._helper.is_alive()
    with pytest.raises(StopIteration):
        next(paced)


def test_paced_hands_on_the_client_streams_failure() -> None:
    def failing() -> Iterator[int]:
        yield 1
        raise RuntimeError("cancelled")

    paced = Paced(failing(), Timeout(5, "idle"))
    assert next(paced) == 1
    with pytest.raises(RuntimeError, match="cancelled"):
        next(paced)


# ---------------------------------------------------------------------------- failed authentications


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def unauthenticated() -> ServiceError:
    return ServiceError(grpc.StatusCode.UNAUTHENTICATED, "x-session-token: does not match the session")


def fail(failures: FailedAuthentications, address: str) -> None:
    with pytest.raises(ServiceError) as refusal, failures.guard(address):
        raise unauthenticated()
    assert refusal.value.code == grpc.StatusCode.UNAUTHENTICATED


def test_an_address_is_refused_after_too_many_failures_until_they_age(caplog: pytest.LogCaptureFixture) -> None:
    clock = Clock()
    failures = FailedAuthentications(3, 60.0, clock)
    with caplog.at_level(logging.WARNING, logger="ogserver.access.failed_auth"):
        for _ in range(3):
            fail(failures, "10.0.0.1")
            clock.now += 1
    with pytest.raises(ServiceError) as refusal, failures.guard("10.0.0.1"):
        pass
    assert refusal.value.code == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert "too many failed authentications from 10.0.0.1 (3 in 60 s); retry in 57 s" in refusal.value.message
    with failures.guard("10.0.0.2"):  # other addresses are not affected
        pass
    clock.now += 57
    with failures.guard("10.0.0.1"):  # the first failure has left the window
        pass
    # One WARNING for the burst (rate limited), naming the address, the reason and the count.
    assert [record.levelno for record in caplog.records] == [logging.WARNING]
    assert "10.0.0.1" in caplog.text and "does not match the session" in caplog.text


def test_failure_logging_reports_what_it_left_out(caplog: pytest.LogCaptureFixture) -> None:
    clock = Clock()
    failures = FailedAuthentications(0, 60.0, clock)  # 0: never refused, still logged
    with caplog.at_level(logging.WARNING, logger="ogserver.access.failed_auth"):
        for _ in range(5):
            fail(failures, "10.0.0.1")
            clock.now += 1
        clock.now += 10
        fail(failures, "10.0.0.1")
    assert len(caplog.records) == 2
    assert "6 failures in the last 60 s, 4 not logged" in caplog.records[1].getMessage()


def test_other_refusals_are_not_counted() -> None:
    failures = FailedAuthentications(1, 60.0, Clock())
    with pytest.raises(ServiceError), failures.guard("10.0.0.1"):
        raise ServiceError(grpc.StatusCode.NOT_FOUND, "session_id: no session")
    with failures.guard("10.0.0.1"):
        pass


@pytest.mark.parametrize(("peer", "address"), [
    ("ipv4:127.0.0.1:5123", "127.0.0.1"), ("ipv6:[::1]:5123", "::1"), ("unix:/tmp/socket", "unix:/tmp/socket"),
])
def test_peer_address_leaves_out_the_port(peer: str, address: str) -> None:
    assert peer_address(peer) == address


# ---------------------------------------------------------------------------- API keys and callers


def test_api_keys_file_round_trip(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:
    assert apikeys.main(["alice"]) == 0
    printed = capsys.readouterr().out.splitlines()
    key = printed[0].rsplit(" ", 1)[1]
    line = printed[1].rsplit(" ", 1)[1]
    path = tmp_path / "keys"
    path.write_text(f"# who may create sessions\n{line}\n\nbob:{apikeys.digest('bobs key')}\n")
    callers = Callers(Access(api_keys_file=str(path)))
    assert not callers.open
    assert callers.identify(key, None) == "key:alice"
    assert callers.identify("bobs key", None) == "key:bob"


@pytest.mark.parametrize(("text", "line"), [("alice\n", 1), ("# ok\nalice:abc\n", 2), (f"a b:{'0' * 64}\n", 1),
                                            (f"a:{'0' * 64}\na:{'1' * 64}\n", 2)])
def test_bad_api_keys_files_are_refused(text: str, line: int) -> None:
    with pytest.raises(ValueError, match=f"keys:{line}: expected a new NAME:SHA256HEX"):
        apikeys.parse(text, "keys")


def test_a_missing_api_keys_file_is_a_settings_error(tmp_path) -> None:
    with pytest.raises(ValueError, match=r"access\.api_keys_file: cannot read"):
        Callers(Access(api_keys_file=str(tmp_path / "missing")))


@pytest.mark.parametrize(("api_key", "message"), [
    ("", "x-api-key: metadata is missing"), ("guess", "x-api-key: not a key this server accepts"),
])
def test_callers_without_a_known_key_are_refused(api_key: str, message: str) -> None:
    callers = Callers(Access(api_keys={"alice": apikeys.digest("secret")}))
    with pytest.raises(ServiceError) as refusal:
        callers.identify(api_key, None)
    assert refusal.value.code == grpc.StatusCode.UNAUTHENTICATED and refusal.value.message == message


def test_a_client_certificate_names_the_caller_and_a_key_takes_precedence(tmp_path) -> None:
    callers = Callers(Access(tls_cert="c", tls_key="k", tls_client_ca="ca", api_keys={"bot": apikeys.digest("k1")}))
    assert callers.identify("", [b"alice"]) == "cert:alice"
    assert callers.identify("k1", [b"alice"]) == "key:bot"


def test_an_open_server_has_one_anonymous_caller() -> None:
    callers = Callers(Access())
    assert callers.open
    assert callers.identify("", None) == callers.identify("any key", None) == ANONYMOUS


# ---------------------------------------------------------------------------- queued bytes


def test_a_frame_waits_until_its_bytes_fit() -> None:
    budget, closed = ByteBudget(100), threading.Event()
    assert budget.acquire(60, closed)
    waiting = threading.Thread(target=budget.acquire, args=(60, closed))
    waiting.start()
    waiting.join(0.3)
    assert waiting.is_alive()  # 120 > 100: held back
    budget.release(60)
    waiting.join(2)
    assert not waiting.is_alive()


def test_one_frame_always_fits_an_empty_budget_and_closing_ends_the_wait() -> None:
    budget, closed = ByteBudget(10), threading.Event()
    assert budget.acquire(1000, closed)
    closed.set()
    assert not budget.acquire(1, closed)


# ---------------------------------------------------------------------------- settings and keepalive


def test_access_settings_from_file_and_flags(tmp_path) -> None:
    path = tmp_path / "server.yaml"
    path.write_text("access:\n  max_sessions_per_client: 2\n  api_keys:\n    alice: " + "a" * 64 + "\n")
    settings = load(path, {"session_idle_seconds": 30, "tls_cert": "server.crt", "tls_key": "server.key",
                           "max_queued_bytes": 1 << 20})
    assert settings.access.max_sessions_per_client == 2 and settings.access.session_idle_seconds == 30.0
    assert settings.access.api_keys == {"alice": "a" * 64} and settings.access.tls_cert == "server.crt"
    assert settings.limits.max_queued_bytes == 1 << 20


@pytest.mark.parametrize(("text", "message"), [
    ("access:\n  tls_cert: a.crt\n", "tls_cert and access.tls_key go together"),
    ("access:\n  tls_client_ca: ca.crt\n", "tls_client_ca needs"),
    ("access:\n  api_keys:\n    alice: abc\n", "api_keys.alice must be the key's sha256"),
    ("access:\n  stream_idle_seconds: -1\n", "access.stream_idle_seconds must be a finite number"),
    ("access:\n  max_concurrent_calls: 0\n", "access.max_concurrent_calls must be an integer >= 1"),
    ("access:\n  metrics_address: 'metrics'\n", "metrics_address must be HOST:PORT"),
    ("limits:\n  max_queued_bytes: 0\n", "limits.max_queued_bytes"),
])
def test_bad_access_settings_are_refused(tmp_path, text: str, message: str) -> None:
    path = tmp_path / "server.yaml"
    path.write_text(text)
    with pytest.raises(ValueError, match=message):
        load(path)


def test_keepalive_is_on_by_default_and_can_be_turned_off() -> None:
    options = dict(keepalive_options(Access()))
    assert options["grpc.keepalive_time_ms"] == 60000 and options["grpc.keepalive_timeout_ms"] == 20000
    assert keepalive_options(Access(keepalive_seconds=0)) == []
