"""Prometheus metrics (``metrics_address``): sessions, frames, mapping rate, queues, ack latency, statuses,
clamped pose corrections.

Counters that the sessions already keep (frames) are read from the registry when scraped, so a
scrape costs nothing while nobody scrapes; what only a call sees (statuses, ack latency) is counted
as it happens. Each server has its own collector registry, so servers in one process do not mix.

The HTTP endpoint serves at most ``max_metrics_connections`` connections at once (a thread each; one
more is closed at once) and ends a connection that has not finished within ``CONNECTION_SECONDS``, so
idle or slow clients cannot fill the mapping process with threads.
"""

from __future__ import annotations

import contextlib
import logging
import socket
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from socketserver import ThreadingMixIn
from typing import Any
from wsgiref.simple_server import WSGIRequestHandler, WSGIServer, make_server

import grpc
from ogapi.v1 import mapping_pb2 as pb
from prometheus_client import CollectorRegistry, Counter, Histogram, make_wsgi_app
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from ogserver.sessions.hosting import SessionHost
from ogserver.throttled_log import ThrottledLog

log = logging.getLogger(__name__)
_throttled = ThrottledLog(log, 10.0)

LATENCY_BUCKETS = (0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 25.0, 60.0, 150.0)
CONNECTION_SECONDS = 5.0  # a scrape's whole connection, request to response


class _Sessions(Collector):
    """What the registry holds, read at scrape time."""

    def __init__(self, registry: SessionHost) -> None:
        self._registry = registry

    def collect(self) -> Iterator[Metric]:
        sessions = self._registry.sessions()
        yield GaugeMetricFamily("ogserver_sessions", "Open sessions", value=len(sessions))
        totals = self._registry.frame_totals()
        frames = CounterMetricFamily(
            "ogserver_frames", "Frames by outcome: accepted into a session, rejected before it, mapped, "
            "or skipped (accepted but never mapped: a realtime session passed over it for a newer frame, the mapper "
            "failed on it or the session closed first)",
            labels=["outcome"])
        for outcome, count in (("accepted", totals.received), ("rejected", totals.rejected),
                               ("mapped", totals.mapped), ("skipped", totals.unmapped)):
            frames.add_metric([outcome], count)
        yield frames
        depth = GaugeMetricFamily("ogserver_session_queue_depth", "Frames queued or being mapped",
                                  labels=["session_id"])
        fps = GaugeMetricFamily("ogserver_session_mapping_fps",
                                "Frames mapped per second, from the first received to the last mapped",
                                labels=["session_id"])
        for session in sessions:
            counters = session.counters()
            depth.add_metric([session.id], counters.pending)
            fps.add_metric([session.id], counters.processing_fps)
        yield depth
        yield fps


class Metrics:
    def __init__(self, registry: SessionHost) -> None:
        self.collectors = CollectorRegistry()
        self.collectors.register(_Sessions(registry))
        self._calls = Counter("ogserver_calls", "Mapping calls by method and final status code",
                              ["method", "code"], registry=self.collectors)
        self._refusals = Counter("ogserver_frame_refusals", "Frames answered with an error ack, by status code",
                                 ["code"], registry=self.collectors)
        self._latency = Histogram("ogserver_ack_latency_seconds", "From reading a frame to its ack",
                                  buckets=LATENCY_BUCKETS, registry=self.collectors)
        self._clamped = Counter("ogserver_clamped_pose_corrections",
                                "Frames whose ack reports a pose correction clamped at the bound "
                                "(poses.max_translation / max_rotation)", registry=self.collectors)

    def call(self, method: str, code: grpc.StatusCode) -> None:
        self._calls.labels(method, code.name).inc()

    def ack(self, ack: pb.FrameAck) -> None:
        if ack.accepted:
            self._latency.observe(ack.latency_seconds)
            if ack.pose_correction.clamped:
                self._clamped.inc()
        else:
            self._refusals.labels(ack.error.code_name).inc()


class _Handler(WSGIRequestHandler):
    timeout = CONNECTION_SECONDS  # for each read and write; _Deadlines bounds the whole connection

    def log_message(self, format: str, *args: Any) -> None:
        """Scrapes are not logged."""


class _Deadlines:
    """One thread that cuts the connections open longer than ``seconds``, however slowly they send."""

    def __init__(self, seconds: float) -> None:
        self._seconds = seconds
        self._open: dict[socket.socket, float] = {}
        self._lock = threading.Lock()
        self._stopped = threading.Event()
        threading.Thread(target=self._run, name="metrics-deadlines", daemon=True).start()

    def add(self, connection: socket.socket) -> None:
        with self._lock:
            self._open[connection] = time.monotonic() + self._seconds

    def remove(self, connection: socket.socket) -> None:
        with self._lock:
            self._open.pop(connection, None)

    def _run(self) -> None:
        while not self._stopped.wait(min(1.0, self._seconds / 4)):
            now = time.monotonic()
            with self._lock:
                late = [connection for connection, deadline in self._open.items() if deadline < now]
            for connection in late:
                with contextlib.suppress(OSError):  # it closed meanwhile
                    connection.shutdown(socket.SHUT_RDWR)

    def stop(self) -> None:
        self._stopped.set()


class _BoundedServer(ThreadingMixIn, WSGIServer):
    """A thread per connection, at most ``limit`` at once, none longer than CONNECTION_SECONDS."""

    daemon_threads = True
    limit = 1

    def server_activate(self) -> None:
        super().server_activate()
        self._slots = threading.BoundedSemaphore(self.limit)
        self.deadlines = _Deadlines(CONNECTION_SECONDS)

    def process_request(self, request: Any, client_address: Any) -> None:
        if not self._slots.acquire(blocking=False):
            _throttled.warning(f"metrics: {self.limit} connections open already; closed one from {client_address[0]}")
            self.shutdown_request(request)
            return
        self.deadlines.add(request)
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._finished(request)
            raise

    def process_request_thread(self, request: Any, client_address: Any) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._finished(request)

    def _finished(self, request: Any) -> None:
        self.deadlines.remove(request)
        self._slots.release()

    def handle_error(self, request: Any, client_address: Any) -> None:
        log.debug("metrics: connection from %s ended", client_address[0], exc_info=True)


@dataclass
class Endpoint:
    """The HTTP server that answers scrapes at /metrics."""

    http: _BoundedServer

    @property
    def port(self) -> int:
        return self.http.server_port

    @classmethod
    def start(cls, address: str, metrics: Metrics, max_connections: int) -> Endpoint:
        host, port = address.rsplit(":", 1)
        try:
            family = socket.getaddrinfo(host.strip("[]"), int(port), type=socket.SOCK_STREAM,
                                        flags=socket.AI_PASSIVE)[0][0]
            server_class = type("Server", (_BoundedServer,), {"address_family": family, "limit": max_connections})
            http = make_server(host.strip("[]"), int(port), make_wsgi_app(metrics.collectors), server_class,
                               handler_class=_Handler)
        except (OSError, ValueError) as error:
            raise ValueError(f"cannot serve metrics on {address}: {error}") from None
        threading.Thread(target=http.serve_forever, name="metrics", daemon=True).start()
        return cls(http)

    def stop(self) -> None:
        self.http.shutdown()
        self.http.server_close()
        self.http.deadlines.stop()
