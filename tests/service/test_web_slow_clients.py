"""Slow clients against the web view's HTTP server: a request head (under TLS, the handshake too) dripping
in a byte at a time is cut off at its deadline, one address cannot hold every connection, so a slowloris
no longer refuses everyone, and a client that takes nothing of its answer does not keep its connection."""

from __future__ import annotations

import socket
import ssl
import time
import urllib.request
from http import HTTPStatus

from ogserver.access.transport import tls_context
from ogserver.http import policy
from ogserver.settings import Access
from ogserver.web import http_server
from ogserver.web.http_server import Answer, Pages

from .certificates import make_ca
from .test_web_requests import HOST, exchange, status, web_server

GOOD = b"GET /static/style.css HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n"


def dripping(port: int, source: str = HOST) -> socket.socket:
    """A connection from ``source`` that has sent the start of a request head."""
    connection = socket.create_connection((HOST, port), timeout=10, source_address=(source, 0))
    connection.sendall(b"GET /static/style.css HTTP/1.1\r\nHost: 127.0.0.1\r\n")
    return connection


def closed_by_server(connection: socket.socket, seconds: float) -> bool:
    connection.settimeout(seconds)
    try:
        return connection.recv(1024) == b""
    except (TimeoutError, ConnectionError):
        return False


def open_seconds(connection: socket.socket, byte: bytes) -> float:
    """How long ``connection`` stays open while ``byte`` is sent every 0.2 s (each read on its own is quick),
    for up to 3 s."""
    start = time.monotonic()
    while time.monotonic() - start < 3.0:
        try:
            connection.sendall(byte)
        except OSError:
            break
        time.sleep(0.2)
    connection.close()
    return time.monotonic() - start


def test_a_request_head_that_drips_in_is_cut_off_at_its_deadline() -> None:
    with web_server(head_seconds=1.0) as server:
        elapsed = open_seconds(dripping(server.port), b"X")
        assert elapsed < 2.5, f"the connection stayed open {elapsed:.1f} s while its head dripped in"


def test_one_address_cannot_hold_every_connection() -> None:
    with web_server() as server:
        held = [dripping(server.port, "127.0.0.2") for _ in range(policy.PER_ADDRESS)]
        try:
            extra = dripping(server.port, "127.0.0.2")
            assert closed_by_server(extra, 5), "a connection beyond the address's share is closed at once"
            extra.close()
            assert status(exchange(server.port, GOOD)) == 200, "another address is still served"
        finally:
            for connection in held:
                connection.close()


def test_under_tls_a_handshake_that_drips_in_counts_against_the_head_deadline(tmp_path) -> None:
    ca = make_ca(tmp_path / "pki")
    access = Access()
    ca.serve(access, mutual=True)
    with web_server(tls=tls_context(access, "live.web_port"), head_seconds=1.0) as server:
        elapsed = open_seconds(socket.create_connection((HOST, server.port), timeout=10), b"\x16")  # a ClientHello
        assert elapsed < 2.5, f"the connection stayed open {elapsed:.1f} s while its TLS handshake dripped in"
        client = ca.clients["alice"]
        trusting = ssl.create_default_context(cafile=str(ca.ca))
        trusting.load_cert_chain(str(client.cert), str(client.key))
        with urllib.request.urlopen(f"https://127.0.0.1:{server.port}/static/style.css", context=trusting,
                                    timeout=10) as response:
            assert response.status == 200  # a prompt handshake and head are served as before


def test_a_response_the_client_takes_nothing_of_ends_its_connection(monkeypatch) -> None:
    big = b"x" * (64 << 20)  # past what the socket buffers and the transport's high-water mark hold
    monkeypatch.setattr(Pages, "answer", lambda pages, *request: Answer(HTTPStatus.OK, big))
    monkeypatch.setattr(http_server, "REQUEST_SECONDS", 1.0)
    with web_server() as server:
        connection = socket.create_connection((HOST, server.port), timeout=10)
        connection.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        connection.sendall(b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        time.sleep(3.0)  # reading nothing
        connection.settimeout(1)
        ended, start = False, time.monotonic()
        while not ended and time.monotonic() - start < 10:
            try:
                ended = connection.recv(1 << 20) == b""
            except TimeoutError:
                break
            except ConnectionError:
                ended = True
        connection.close()
        assert ended, "the server kept a connection whose client took nothing"
