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
from ogserver.access.failed_auth import (
    LOG_INTERVAL,
    LOG_LINES,
    MAX_ADDRESSES,
    FailedAuthentications,
    Window,
    peer_address,
)
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


def fail(failures: FailedAuthentications, address: str) -> ServiceError:
    """A wrong credential from ``address``: how the server answers it."""
    with pytest.raises(ServiceError) as refusal, failures.guard(address):
        raise unauthenticated()
    return refusal.value


def succeed(failures: FailedAuthentications, address: str) -> None:
    with failures.guard(address):
        pass  # the credential was right


def test_a_right_credential_passes_whatever_others_sent_from_its_address() -> None:
    """Clients behind one NAT share an address: one failing must not lock the others out."""
    clock = Clock()
    failures = FailedAuthentications(3, 60.0, 100, clock)
    assert [fail(failures, "10.0.0.1").code for _ in range(3)] == [grpc.StatusCode.UNAUTHENTICATED] * 3
    refusal = fail(failures, "10.0.0.1")
    assert refusal.code == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert refusal.message == ("too many failed authentications from 10.0.0.1 (3 in 60 s); "
                               "x-session-token: does not match the session")
    succeed(failures, "10.0.0.1")
    assert fail(failures, "10.0.0.2").code == grpc.StatusCode.UNAUTHENTICATED  # other addresses: their own count
    clock.now += 120  # two windows later the address starts afresh
    assert fail(failures, "10.0.0.1").code == grpc.StatusCode.UNAUTHENTICATED


def test_many_addresses_are_limited_together() -> None:
    """50 addresses x 19 wrong credentials: none past its own limit of 20, the server past its 200."""
    failures = FailedAuthentications(20, 60.0, 200, Clock())
    codes = [fail(failures, f"10.0.{number}.1").code for _ in range(19) for number in range(50)]
    assert codes.count(grpc.StatusCode.UNAUTHENTICATED) == 200
    assert codes.count(grpc.StatusCode.RESOURCE_EXHAUSTED) == 750
    assert "from all addresses (200 in 60 s)" in fail(failures, "10.1.0.1").message
    succeed(failures, "10.1.0.1")


def test_failures_age_out_of_the_window() -> None:
    clock = Clock()
    failures = FailedAuthentications(0, 60.0, 10, clock)
    for _ in range(10):
        fail(failures, "10.0.0.1")
    assert fail(failures, "10.0.0.2").code == grpc.StatusCode.RESOURCE_EXHAUSTED
    clock.now += 90  # half of the previous window's 11 failures still counted
    assert fail(failures, "10.0.0.2").code == grpc.StatusCode.UNAUTHENTICATED


def test_the_address_table_stays_bounded() -> None:
    clock = Clock()
    failures = FailedAuthentications(3, 60.0, 0, clock)
    for _ in range(3):
        fail(failures, "10.0.0.1")
    for number in range(2 * MAX_ADDRESSES):  # every one of them failing within the window
        fail(failures, f"10.{number >> 16}.{(number >> 8) & 255}.{number & 255}")
        if number % 1000 == 0:
            fail(failures, "10.0.0.1")  # it keeps failing: the least recently failed go first
    assert len(failures) == MAX_ADDRESSES
    assert fail(failures, "10.0.0.1").code == grpc.StatusCode.RESOURCE_EXHAUSTED


def test_a_window_estimates_the_events_of_the_last_seconds() -> None:
    window = Window(10.0, 0.0)
    for now in (1.0, 2.0, 3.0, 4.0):
        window.add(now)
    assert window.recent(9.0) == 4
    assert window.recent(12.5) == pytest.approx(3.0)  # a quarter of the previous window has left
    assert window.recent(30.0) == 0
    assert Window(0.0, 0.0).recent(1.0) == 0  # no window: nothing is ever counted


def test_failures_are_logged_without_flooding_the_log(caplog: pytest.LogCaptureFixture) -> None:
    clock = Clock()
    failures = FailedAuthentications(3, 60.0, 0, clock)
    with caplog.at_level(logging.WARNING, logger="ogserver.access.failed_auth"):
        for _ in range(5):
            fail(failures, "10.0.0.1")
            clock.now += 1
        clock.now += 10
        fail(failures, "10.0.0.1")
    assert len(caplog.records) == 2  # one for the burst, naming the address, the reason and the counts
    first, second = (record.getMessage() for record in caplog.records)
    assert first == ("authentication failed from 10.0.0.1: x-session-token: does not match the session "
                     "(1 from this address; 1 from all addresses in the last 60 s)")
    assert second.startswith("authentication failed from 10.0.0.1: too many failed authentications from 10.0.0.1")
    assert second.endswith("(5 from this address since its previous line; 6 from all addresses in the last 60 s)")


def test_many_addresses_share_a_bounded_number_of_log_lines(caplog: pytest.LogCaptureFixture) -> None:
    clock = Clock()
    failures = FailedAuthentications(0, 60.0, 0, clock)
    with caplog.at_level(logging.WARNING, logger="ogserver.access.failed_auth"):
        for number in range(50):
            fail(failures, f"10.0.0.{number}")
        assert len(caplog.records) == LOG_LINES
        clock.now += LOG_INTERVAL
        fail(failures, "10.0.0.49")
    assert caplog.records[-1].getMessage().endswith("(2 from this address; 51 from all addresses in the last 60 s)")


def test_other_refusals_are_not_counted() -> None:
    failures = FailedAuthentications(1, 60.0, 1, Clock())
    with pytest.raises(ServiceError), failures.guard("10.0.0.1"):
        raise ServiceError(grpc.StatusCode.NOT_FOUND, "session_id: no session")
    assert fail(failures, "10.0.0.1").code == grpc.StatusCode.UNAUTHENTICATED


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
    ("access:\n  stream_idle_seconds: -1\n", "access.stream_idle_seconds is out of range: must be >= 0 and finite"),
    ("access:\n  max_concurrent_calls: 0\n", "access.max_concurrent_calls is out of range: must be >= 1, got 0"),
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
