"""Prometheus metrics (``metrics_address``): sessions, frames, mapping rate, queues, ack latency, statuses,
clamped pose corrections.

Counters that the sessions already keep (frames) are read from the registry when scraped, so a
scrape costs nothing while nobody scrapes; what only a call sees (statuses, ack latency) is counted
as it happens. Each server has its own collector registry, so servers in one process do not mix.

The HTTP endpoint serves at most ``max_metrics_connections`` connections at once (one more is closed at
once) under the policy of every HTTP port of the server (``ogserver.http.policy``): a request's head within
``CONNECTION_SECONDS``, idle connections closed as soon, and only requests whose ``Host`` names the server.
"""

from __future__ import annotations

import asyncio
from collections.abc import Iterable, Iterator

import grpc
from aiohttp import web
from ogapi.v1 import mapping_pb2 as pb
from prometheus_client import CollectorRegistry, Counter, Histogram
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.exposition import choose_encoder
from prometheus_client.registry import Collector

from ogserver.http.policy import PER_ADDRESS, Policy
from ogserver.http.server import HttpServer
from ogserver.sessions.hosting import SessionHost
from ogserver.web.hosts import HostPolicy

LATENCY_BUCKETS = (0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 25.0, 60.0, 150.0)
CONNECTION_SECONDS = 5.0  # a scrape's request head; an idle or stalled connection is closed as soon


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


class Endpoint:
    """The HTTP server that answers scrapes at /metrics (every path, as before), on the listener every HTTP
    port of the server shares (``ogserver.http``)."""

    def __init__(self, address: str, metrics: Metrics, max_connections: int, hosts: Iterable[str] = ()) -> None:
        host, port = address.rsplit(":", 1)
        self._collectors = metrics.collectors
        app = web.Application()
        app.router.add_get("/{path:.*}", self._scrape)
        policy = Policy(max_connections, min(PER_ADDRESS, max_connections), CONNECTION_SECONDS, CONNECTION_SECONDS,
                        HostPolicy.serving(host, hosts))
        try:
            self.http = HttpServer("metrics", host, int(port), app, policy)
        except (OSError, ValueError) as error:
            raise ValueError(f"cannot serve metrics on {address}: {error}") from None
        self.port: int = self.http.port

    @classmethod
    def start(cls, address: str, metrics: Metrics, max_connections: int, hosts: Iterable[str] = ()) -> Endpoint:
        endpoint = cls(address, metrics, max_connections, hosts)
        endpoint.http.start()
        return endpoint

    async def _scrape(self, request: web.Request) -> web.Response:
        """The collectors read on a worker thread (they take the sessions' locks), in the format the scraper
        accepts (Prometheus text, or OpenMetrics), only the ``name[]`` families where it names some."""
        encoder, kind = choose_encoder(request.headers.get("Accept", ""))
        names = request.query.getall("name[]", [])
        collectors = self._collectors.restricted_registry(names) if names else self._collectors
        body = await asyncio.get_running_loop().run_in_executor(None, encoder, collectors)
        return web.Response(body=body, headers={"Content-Type": kind})

    def stop(self) -> None:
        self.http.stop()
