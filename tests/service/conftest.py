"""A server for the integration tests: $OGMAP_SERVER when set (the container test), else a subprocess."""

from __future__ import annotations

import os
from collections.abc import Iterator
from dataclasses import dataclass

import grpc
import pytest
from ogapi.v1 import mapping_pb2_grpc as pb_grpc
from ogclient.connection import connect
from ogclient.local_server import LocalServer

from .scene import TEST_SERVER_CONFIG


@dataclass
class ServerHandle:
    address: str
    channel: grpc.Channel
    stub: pb_grpc.MappingStub
    local: LocalServer | None


def start_local(record_dir, *extra: str) -> LocalServer:
    return LocalServer(record_dir, "--config", str(TEST_SERVER_CONFIG), "--device", "cpu", *extra).start()


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerHandle]:
    """Started once per module; stopped with SIGTERM (the graceful path) at its end."""
    external = os.environ.get("OGMAP_SERVER")
    local = None if external else start_local(tmp_path_factory.mktemp("recordings"))
    address = external or local.address
    channel, stub = connect(address, timeout=60.0)
    try:
        yield ServerHandle(address, channel, stub, local)
    finally:
        channel.close()
        if local is not None:
            local.stop()
