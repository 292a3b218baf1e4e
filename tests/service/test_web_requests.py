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
from ogserver.web.http_server import Handler, WebServer
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
    def fails(handler) -> None:
        raise RuntimeError("a handler's own bug")

    monkeypatch.setattr(Handler, "do_GET", fails)
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
