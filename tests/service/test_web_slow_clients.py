"""Slow clients against the web view's HTTP server: a request head dripping in a byte at a time is cut off
at its deadline, and one address cannot hold every connection, so a slowloris no longer refuses everyone."""

from __future__ import annotations

import socket
import time

from ogserver.web import deadlines

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


def test_a_request_head_that_drips_in_is_cut_off_at_its_deadline() -> None:
    with web_server() as server:
        server.head_seconds = 1.0
        connection = dripping(server.port)
        start = time.monotonic()
        while time.monotonic() - start < 3.0:  # a header byte every 0.2 s: each read on its own is quick
            try:
                connection.sendall(b"X")
            except OSError:
                break
            time.sleep(0.2)
        elapsed = time.monotonic() - start
        assert elapsed < 2.5, f"the connection stayed open {elapsed:.1f} s while its head dripped in"
        connection.close()


def test_one_address_cannot_hold_every_connection() -> None:
    with web_server() as server:
        held = [dripping(server.port, "127.0.0.2") for _ in range(deadlines.PER_ADDRESS)]
        try:
            extra = dripping(server.port, "127.0.0.2")
            assert closed_by_server(extra, 5), "a connection beyond the address's share is closed at once"
            extra.close()
            assert status(exchange(server.port, GOOD)) == 200, "another address is still served"
        finally:
            for connection in held:
                connection.close()
