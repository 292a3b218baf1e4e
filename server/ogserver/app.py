"""Assemble the gRPC server: the mapping service, standard health checking and reflection."""

from __future__ import annotations

import dataclasses
import logging
import threading
from concurrent import futures
from dataclasses import dataclass
from pathlib import Path

import ogmapping  # noqa: F401 (before torch: it sets the OpenMP wait policy torch's pool reads at start)

# isort: split
import grpc
import torch
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from ogapi import SERVICE_NAME

from ogmapping.runtime.profile import resolve_device
from ogmapping.warmup import warm_up
from ogserver.access import transport
from ogserver.access.call_gate import HEADROOM, CallGate
from ogserver.access.callers import Callers
from ogserver.access.failed_auth import FailedAuthentications
from ogserver.access.viewers import Viewers
from ogserver.api import reflection, wire
from ogserver.api.servicer import MappingService
from ogserver.event_loop import EventLoop
from ogserver.live.foxglove_ws import FoxgloveServer
from ogserver.live.port_access import port_access
from ogserver.live.publisher import LiveView
from ogserver.metrics import Endpoint, Metrics
from ogserver.recording import disk
from ogserver.sessions.expiry import Expiry
from ogserver.sessions.hosting import Closed, SessionHost
from ogserver.sessions.registry import Registry
from ogserver.sessions.resume import resume_all
from ogserver.settings import Settings
from ogserver.web.http_server import WebServer
from ogserver.web.serving import start_web

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Stopped:
    closed: list[Closed]
    complete: bool  # False if gRPC or a session's frame was still running at the deadline


@dataclass
class Server:
    grpc_server: grpc.aio.Server
    loop: EventLoop  # the one the gRPC server runs on
    pool: futures.ThreadPoolExecutor  # where the mapping calls run
    registry: SessionHost
    health: health.aio.HealthServicer
    port: int
    expiry: Expiry
    metrics: Endpoint | None  # the /metrics HTTP server, when metrics_address is set
    live: LiveView | None  # renders and point clouds for Foxglove and the recordings, unless views are off
    web: WebServer | None = None  # the web view (live.web_port)

    def stop(self, grace: float, timeout: float) -> Stopped:
        """Report NOT_SERVING, let calls in flight finish (up to ``grace``), wait up to ``timeout`` more
        for gRPC to stop, then close every session, waiting up to ``timeout`` for frames being mapped."""
        self.expiry.stop()
        self.loop.run(self.health.enter_graceful_shutdown())
        try:
            self.loop.run(self.grpc_server.stop(grace), grace + timeout)
            grpc_stopped = True
        except TimeoutError:
            grpc_stopped = False
        if not grpc_stopped:
            log.warning("gRPC calls were still running %.1f s after the grace; closing the sessions anyway", timeout)
        if self.live is not None:
            self.live.stop()
        if self.web is not None:
            self.web.stop()
        closed = self.registry.close_all(timeout)
        drained = _drain(self.pool, timeout)
        if drained:  # else calls still running may need the loop to end theirs
            self.loop.close()
        if self.metrics is not None:
            self.metrics.stop()
        return Stopped(closed, grpc_stopped and drained and all(item.stopped for item in closed))


def _drain(pool: futures.ThreadPoolExecutor, timeout: float) -> bool:
    """Whether the calls still running in the pool ended within ``timeout``, their sessions closed."""
    waiter = threading.Thread(target=pool.shutdown, name="grpc-drain", daemon=True)
    waiter.start()
    waiter.join(timeout)
    return not waiter.is_alive()


def build(settings: Settings) -> Server:
    """A started server; ``port`` is the bound one (useful with port 0)."""
    disk.check_writable(Path(settings.record_dir))
    device = str(resolve_device(settings.device))
    torch.set_num_threads(settings.threads())
    limits, access = settings.limits, settings.access
    callers = Callers(access)
    credentials = transport.server_credentials(access)
    # Mapping calls run in a thread pool, held to max_concurrent_calls (a frame stream holds a thread for
    # its lifetime); the headroom refuses calls over the limit. A call waiting for its client holds no
    # thread, and health checks and reflection are served in the event loop, beside the pool.
    pool = futures.ThreadPoolExecutor(max_workers=access.max_concurrent_calls + HEADROOM, thread_name_prefix="grpc")
    options = [
        ("grpc.max_receive_message_length", limits.max_message_bytes),
        ("grpc.max_send_message_length", limits.max_message_bytes),
        ("grpc.max_concurrent_streams", access.max_streams_per_connection),
        *transport.keepalive_options(access),
    ]
    registry = _host(settings, device)
    metrics = Metrics(registry)
    loop = EventLoop("grpc-loop")
    gate = CallGate(access.max_concurrent_calls, metrics.call, access.request_seconds, pool, access.response_seconds,
                    access.max_calls_per_caller)
    try:
        server, health_servicer, port = loop.run(_grpc_server(settings, options, gate, pool, credentials))
    except RuntimeError:  # grpc.aio's "Failed to bind to address"
        port = 0
    if port == 0:
        loop.close()
        pool.shutdown()
        raise ValueError(f"could not bind {settings.address}")
    wire.add_mapping_service(MappingService(registry, callers, metrics), server)
    endpoint = Endpoint.start(access.metrics_address, metrics, access.max_metrics_connections,
                              settings.live.web_hosts) \
        if access.metrics_address else None
    # The live views see the sessions of this process or of its workers (cluster mode has none).
    viewers = Viewers(registry, callers, FailedAuthentications(
        access.max_auth_failures, access.auth_failure_window_seconds, access.max_auth_failures_total)) \
        if not settings.cluster else None
    live = _live_view(settings, viewers) if viewers is not None else None
    web = start_web(settings, viewers) if settings.live.web_port >= 0 and viewers is not None else None
    loop.run(server.start())
    log.info("device %s, %d torch threads, record dir %s", device, torch.get_num_threads(), settings.record_dir)
    _announce_access(settings, f"{settings.address.rsplit(':', 1)[0]}:{port}", callers, credentials is not None,
                     endpoint)
    return Server(server, loop, pool, registry, health_servicer, port, Expiry(registry).start(), endpoint,
                  live.start() if live is not None else None, web)


async def _grpc_server(
    settings: Settings, options: list[tuple[str, int]], gate: CallGate, pool: futures.Executor,
    credentials: grpc.ServerCredentials | None,
) -> tuple[grpc.aio.Server, health.aio.HealthServicer, int]:
    """The server (created in its event loop) with health checking and reflection, and its bound port."""
    server = grpc.aio.server(migration_thread_pool=pool, options=options, interceptors=[gate])
    health_servicer = health.aio.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    for name in ("", SERVICE_NAME):
        await health_servicer.set(name, health_pb2.HealthCheckResponse.SERVING)
    reflection.enable(server, (SERVICE_NAME, health.SERVICE_NAME))
    if credentials is None:
        return server, health_servicer, server.add_insecure_port(settings.address)
    return server, health_servicer, server.add_secure_port(settings.address, credentials)


def _host(settings: Settings, device: str) -> SessionHost:
    """Where sessions live: in this process (resuming those a crashed server left, before serving, so a
    client never finds its session missing while it comes back), in worker processes (``--workers``), or
    in Ray actors (``--cluster``)."""
    if settings.cluster:
        try:
            from ogserver.cluster.host import ClusterHost
        except ImportError as error:
            raise RuntimeError(f"--cluster needs Ray, the 'cluster' extra (pip install -e '.[cluster]'): {error}") \
                from None
        return ClusterHost(settings)
    if settings.workers:
        from ogserver.workers.host import WorkerHost

        return WorkerHost(settings, device)  # each worker warms up, and --resume places the sessions on them
    if settings.warm_up:
        log.info("warming up on %s (a first start compiles the kernels, minutes on a slow CPU; `make venv` or "
                 "python -m ogmapping.warmup does it ahead)", device)
        seconds = warm_up(device, progress=lambda stage, elapsed: log.info("warm-up: %s, %.1f s", stage, elapsed))
        log.info("warmed up on %s: %.1f s", device, seconds)
    registry = Registry(settings, device)
    if settings.resume:
        resume_all(registry)
    return registry


def _live_view(settings: Settings, viewers: Viewers) -> LiveView | None:
    """The live view's thread, with a Foxglove server when one is asked for; None when nothing would use it.
    With worker processes, each worker records its own sessions' views, and this one only publishes."""
    live, registry = settings.live, viewers.registry
    if settings.workers:
        live = dataclasses.replace(live, record_views=False)
    if not live.view_seconds or not (live.foxglove or live.record_views):
        return None
    if not live.foxglove:
        return LiveView(registry, live, None)
    port = port_access(settings)
    foxglove = FoxgloveServer(live.foxglove_host, live.foxglove_port, port.gate(viewers), port.tls)
    url = port.url(live.foxglove_host, foxglove.port)
    operator = f"; ?token= the contents of {live.foxglove_token_file} sees every session" if port.token else ""
    if viewers.callers.open:
        local = live.foxglove_host in ("127.0.0.1", "localhost", "::1")
        log.log(logging.INFO if local else logging.WARNING, "Foxglove live view on %s (an open server: anyone who "
                "reaches it sees every session's images and map%s)", url, operator)
    else:
        log.info("Foxglove live view on %s (?key=API_KEY for the sessions it owns, ?token=SESSION_TOKEN for its one "
                 "session%s)", url, operator)
    return LiveView(registry, live, foxglove)


def _announce_access(settings: Settings, bound: str, callers: Callers, tls: bool, metrics: Endpoint | None) -> None:
    """Say in the log who may call at ``bound`` (HOST:PORT with the port bound, not 0); warn when anyone who
    reaches a non-local address may."""
    transport_name = "mutual TLS" if settings.access.tls_client_ca else "TLS" if tls else "plaintext (no TLS)"
    if callers.open:
        level = logging.INFO if settings.address.startswith(("127.", "localhost:", "[::1]:")) else logging.WARNING
        log.log(level, "%s, open: no API keys or client certificates, so anyone who reaches %s may create, "
                "restore and list sessions", transport_name, bound)
    else:
        log.info("%s; creating, restoring and listing sessions need %s", transport_name, callers.describe())
    if metrics is not None:
        host = settings.access.metrics_address.rsplit(":", 1)[0]
        local = host in ("127.0.0.1", "localhost", "[::1]")
        exposed = "" if local else " (no authentication: anyone who reaches it reads session ids and counts)"
        log.log(logging.INFO if local else logging.WARNING, "Prometheus metrics on http://%s:%d/metrics%s", host,
                metrics.port, exposed)
