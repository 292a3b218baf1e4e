"""Assemble the gRPC server: the mapping service, standard health checking and reflection."""

from __future__ import annotations

import logging
from concurrent import futures
from dataclasses import dataclass
from pathlib import Path

import ogmapping  # noqa: F401 (before torch: it sets the OpenMP wait policy torch's pool reads at start)

# isort: split
import grpc
import torch
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from ogapi import SERVICE_NAME

from ogmapping.profile import resolve_device
from ogmapping.warmup import warm_up
from ogserver import reflection, storage, wire
from ogserver.registry import Closed, Registry
from ogserver.service import MappingService
from ogserver.settings import Settings

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Stopped:
    closed: list[Closed]
    complete: bool  # False if gRPC or a session's frame was still running at the deadline


@dataclass
class Server:
    grpc_server: grpc.Server
    registry: Registry
    health: health.HealthServicer
    port: int

    def stop(self, grace: float, timeout: float) -> Stopped:
        """Report NOT_SERVING, let calls in flight finish (up to ``grace``), wait up to ``timeout`` more
        for gRPC to stop, then close every session, waiting up to ``timeout`` for frames being mapped."""
        self.health.enter_graceful_shutdown()
        grpc_stopped = self.grpc_server.stop(grace).wait(grace + timeout)
        if not grpc_stopped:
            log.warning("gRPC calls were still running %.1f s after the grace; closing the sessions anyway", timeout)
        closed = self.registry.close_all(timeout)
        return Stopped(closed, grpc_stopped and all(item.stopped for item in closed))


def build(settings: Settings) -> Server:
    """A started server; ``port`` is the bound one (useful with port 0)."""
    storage.check_writable(Path(settings.record_dir))
    device = str(resolve_device(settings.device))
    torch.set_num_threads(settings.threads())
    limits = settings.limits
    workers = 2 * limits.max_sessions + 8  # each frame stream holds a thread for its lifetime
    options = [
        ("grpc.max_receive_message_length", limits.max_message_bytes),
        ("grpc.max_send_message_length", limits.max_message_bytes),
    ]
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=workers, thread_name_prefix="grpc"), options=options)
    if settings.warm_up:
        log.info("warming up on %s: %.1f s", device, warm_up(device))
    registry = Registry(settings, device)
    wire.add_mapping_service(MappingService(registry), server)
    health_servicer = health.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    for name in ("", SERVICE_NAME):
        health_servicer.set(name, health_pb2.HealthCheckResponse.SERVING)
    reflection.enable(server, (SERVICE_NAME, health.SERVICE_NAME))
    port = server.add_insecure_port(settings.address)
    if port == 0:
        raise ValueError(f"could not bind {settings.address}")
    server.start()
    log.info("device %s, %d torch threads, record dir %s", device, torch.get_num_threads(), settings.record_dir)
    return Server(server, registry, health_servicer, port)
