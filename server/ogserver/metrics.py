"""Prometheus metrics (``metrics_address``): sessions, frames, mapping rate, queues, ack latency, statuses.

Counters that the sessions already keep (frames) are read from the registry when scraped, so a
scrape costs nothing while nobody scrapes; what only a call sees (statuses, ack latency) is counted
as it happens. Each server has its own collector registry, so servers in one process do not mix.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from wsgiref.simple_server import WSGIServer

import grpc
from ogapi.v1 import mapping_pb2 as pb
from prometheus_client import CollectorRegistry, Counter, Histogram, start_http_server
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from ogserver.sessions.hosting import SessionHost

LATENCY_BUCKETS = (0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 25.0, 60.0, 150.0)


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

    def call(self, method: str, code: grpc.StatusCode) -> None:
        self._calls.labels(method, code.name).inc()

    def ack(self, ack: pb.FrameAck) -> None:
        if ack.accepted:
            self._latency.observe(ack.latency_seconds)
        else:
            self._refusals.labels(ack.error.code_name).inc()


@dataclass
class Endpoint:
    """The HTTP server that answers scrapes at /metrics."""

    http: WSGIServer

    @property
    def port(self) -> int:
        return self.http.server_port

    @classmethod
    def start(cls, address: str, metrics: Metrics) -> Endpoint:
        host, port = address.rsplit(":", 1)
        try:
            http, _ = start_http_server(int(port), host.strip("[]"), registry=metrics.collectors)
        except (OSError, ValueError) as error:
            raise ValueError(f"cannot serve metrics on {address}: {error}") from None
        return cls(http)

    def stop(self) -> None:
        self.http.shutdown()
        self.http.server_close()
