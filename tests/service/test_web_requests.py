"""The web view's HTTP server against odd requests, without a mapping server behind it: a request line that
the file lookup cannot take gets a short answer and no traceback in the log."""

from __future__ import annotations

import logging
import socket
from collections.abc import Iterator
from contextlib import contextmanager
from types import SimpleNamespace

import pytest
from ogserver.web.catalogue import Credential
from ogserver.web.hosts import HostPolicy
from ogserver.web.http_server import Pages, WebServer
from ogserver.web.maps import Busy

HOST = "127.0.0.1"
MAP_ID = "room"
TOKEN = "the-token"


class Catalogue:
    """One map, shown to whoever holds ``TOKEN``; its page and index need nothing more of it."""

    asks_credential = True

    def __init__(self) -> None:
        self.busy = Busy()
        self.view = SimpleNamespace(source=SimpleNamespace(id=MAP_ID, label="a room"))

    def visible(self, credential: Credential) -> list:
        return [self.view] if TOKEN in (credential.token, credential.key) else []

    def find(self, map_id: str, credential: Credential):
        return next((view for view in self.visible(credential) if view.source.id == map_id), None)


@contextmanager
def web_server(**options) -> Iterator[WebServer]:
    server = WebServer(HOST, 0, Catalogue(), **options).start()
    try:
        yield server
    finally:
        server.stop()


def exchange(port: int, request: bytes) -> bytes:
    """The server's whole answer to one raw request on a connection of its own."""
    with socket.create_connection((HOST, port), timeout=10) as connection:
        connection.sendall(request)
        answer = b""
        while chunk := connection.recv(65536):
            answer += chunk
    return answer


def status(answer: bytes) -> int:
    return int(answer.split(b" ", 2)[1]) if answer.startswith(b"HTTP/1.") else 0


@pytest.mark.parametrize("target", [
    pytest.param(b"/static/a%00b", id="percent-encoded NUL"),
    pytest.param(b"/static/a\x00b", id="NUL"),
    pytest.param(b"/vendor/three/\x00", id="NUL in vendor"),
    pytest.param(b"/static/" + b"a" * 5000, id="over-long name"),
    pytest.param(b"/static/" + b"a/" * 3000 + b"b", id="over-long path"),
    pytest.param(b"/static/\xff\xfe\xc3(", id="not UTF-8"),
    pytest.param(b"/static/%ff%fe", id="percent-encoded not UTF-8"),
    pytest.param(b"//[x/static/style.css", id="unparsable netloc"),
    pytest.param(b"/map/room\x00?token=" + TOKEN.encode(), id="NUL in a map's path"),
])
def test_a_path_the_lookup_cannot_take_is_refused_without_a_traceback(target: bytes, capfd, caplog) -> None:
    caplog.set_level(logging.DEBUG, logger="ogserver")
    with web_server() as server:
        answer = exchange(server.port, b"GET " + target + b" HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
        assert status(exchange(server.port, b"GET /static/style.css HTTP/1.1\r\nHost: localhost\r\n"
                                            b"Connection: close\r\n\r\n")) == 200  # still serving
    assert status(answer) in (400, 404), answer[:200]
    assert len(answer) < 1000
    out, err = capfd.readouterr()
    assert "Traceback" not in out + err and err == ""
    assert not any(record.exc_info or record.levelno >= logging.WARNING for record in caplog.records)


def test_what_escapes_a_handler_is_one_throttled_log_line(monkeypatch, capfd, caplog) -> None:
    def fails(pages, *request) -> None:
        raise RuntimeError("a handler's own bug")

    monkeypatch.setattr(Pages, "answer", fails)
    with web_server() as server:
        for _ in range(3):
            exchange(server.port, b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
    assert capfd.readouterr().err == ""
    failures = [record.getMessage() for record in caplog.records if "a handler's own bug" in record.getMessage()]
    assert len(failures) <= 1 and not any(record.exc_info for record in caplog.records)


def headers(answer: bytes) -> dict[str, str]:
    lines = answer.split(b"\r\n\r\n", 1)[0].decode("latin-1").split("\r\n")[1:]
    return {name.lower(): value.strip() for name, _, value in (line.partition(":") for line in lines)}


def test_a_page_reached_with_a_credential_is_not_cached_and_static_files_are() -> None:
    with web_server() as server:
        def get(target: str) -> bytes:
            return exchange(server.port, f"GET {target} HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n"
                            .encode())

        for query in (f"?token={TOKEN}", f"?key={TOKEN}"):
            page = get(f"/map/{MAP_ID}{query}")
            assert status(page) == 200 and b"<html" in page.lower()
            assert headers(page)["cache-control"] == "no-store"
        style = get("/static/style.css")
        assert status(style) == 200 and headers(style)["cache-control"].startswith("max-age=")


def test_the_host_policy_of_a_server_on_every_address_answers_only_its_own_names() -> None:
    machine = lambda: ("MapHost", "maphost.lan.")  # noqa: E731
    policy = HostPolicy.serving("0.0.0.0", ["maps.example.org", ".lab.example.net"], machine)
    for host in ("localhost", "localhost:8080", "LOCALHOST.", "app.localhost:1", "127.0.0.1", "127.0.0.1:80",
                 "[::1]:8080", "[::1]", "10.1.2.3:8080", "[fe80::1]", "0.0.0.0:80", "maphost", "maphost.lan:8080",
                 "maps.example.org", "Maps.Example.Org.:443", "lab.example.net", "a.b.lab.example.net:9"):
        assert policy.allows(host), host
    for host in ("", " ", "evil.example", "evil.example:8080", "localhost.evil.example", "maps.example.org.evil",
                 "evilmaps.example.org", "example.org", "notlab.example.net", "maphost.evil", "10.1.2.3.evil",
                 "[::1", "[evil]:80", "a b", "maps.example.org:port", "user@maps.example.org", "127.0.0.1/x"):
        assert not policy.allows(host), host


def test_a_server_on_loopback_answers_loopback_and_listed_names_and_does_not_look_up_its_own() -> None:
    def machine() -> tuple[str, ...]:
        raise AssertionError("a loopback server needs no host names of the machine's")

    policy = HostPolicy.serving("127.0.0.1", ["maps.example.org"], machine)
    assert policy.allows("127.0.0.1:8080") and policy.allows("localhost") and policy.allows("maps.example.org")
    assert not policy.allows("evil.example")
    assert HostPolicy.serving("[::1]", (), machine).allows("[::1]:1")
    assert not HostPolicy.serving("10.0.0.5", (), lambda: ["maphost"]).allows("evil.example")


def test_a_request_for_a_host_not_allowed_gets_403_and_no_data() -> None:
    with web_server(hosts=["maps.example.org"]) as server:
        def get(host: str) -> bytes:
            return exchange(server.port, f"GET /?token={TOKEN} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n\r\n"
                            .encode())

        for host in ("maps.example.org", "maps.example.org:8080", "localhost", f"127.0.0.1:{server.port}"):
            answer = get(host)
            assert status(answer) == 200 and MAP_ID.encode() in answer, host
        for host in ("evil.example", "maphost.example.org"):
            answer = get(host)
            assert status(answer) == 403 and MAP_ID.encode() not in answer and len(answer) < 600, host
        missing = exchange(server.port, f"GET /?token={TOKEN} HTTP/1.0\r\n\r\n".encode())
        assert status(missing) == 403 and MAP_ID.encode() not in missing
        page = exchange(server.port, f"GET /map/{MAP_ID}?token={TOKEN} HTTP/1.1\r\nHost: evil.example\r\n"
                                     f"Connection: close\r\n\r\n".encode())
        assert status(page) == 403
