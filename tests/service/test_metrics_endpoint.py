"""The /metrics endpoint against clients that connect and send nothing: a bounded number of threads,
idle connections cut, and scrapes answered again once they are; a request naming another host is refused
(DNS rebinding), as on the web view."""

from __future__ import annotations

import socket
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from .inprocess import serving, settings

IDLE_CONNECTIONS = 200
MAX_CONNECTIONS = 16


def scrape(port: int, within: float) -> str:
    """The page, retried while the endpoint is full, for up to ``within`` seconds."""
    deadline = time.monotonic() + within
    while True:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=5) as page:
                return page.read().decode()
        except (urllib.error.URLError, ConnectionError, TimeoutError):
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def test_idle_metrics_connections_hold_few_threads_and_are_cut(tmp_path: Path) -> None:
    configured = settings(tmp_path)
    configured.access.metrics_address = "127.0.0.1:0"
    configured.access.max_metrics_connections = MAX_CONNECTIONS
    with serving(configured) as running:
        port = running.server.metrics.port
        before = threading.active_count()
        idle = [socket.create_connection(("127.0.0.1", port), timeout=5) for _ in range(IDLE_CONNECTIONS)]
        try:
            time.sleep(1.0)
            assert threading.active_count() - before <= MAX_CONNECTIONS + 2
            start = time.monotonic()
            assert "ogserver_sessions 0.0" in scrape(port, within=15.0)
            assert time.monotonic() - start < 12.0
            cut = 0
            for connection in idle:
                try:
                    cut += connection.recv(1) == b""
                except ConnectionResetError:
                    cut += 1
            assert cut == IDLE_CONNECTIONS  # closed at once when over the limit, or after the deadline
        finally:
            for connection in idle:
                connection.close()


def test_metrics_answer_only_requests_naming_the_server(tmp_path: Path) -> None:
    configured = settings(tmp_path)
    configured.access.metrics_address = "127.0.0.1:0"
    with serving(configured) as running:
        url = f"http://127.0.0.1:{running.server.metrics.port}/metrics"
        with urllib.request.urlopen(urllib.request.Request(url, headers={"Host": "localhost"}), timeout=5) as page:
            assert "ogserver_sessions" in page.read().decode()
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(urllib.request.Request(url, headers={"Host": "evil.example"}), timeout=5)
        assert refused.value.code == 403 and b"ogserver_" not in refused.value.read()
