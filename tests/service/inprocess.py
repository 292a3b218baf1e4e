"""An ogserver inside the test process, built from Settings: for tests of settings the shared server lacks."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import grpc
from ogapi.v1 import mapping_pb2_grpc as pb_grpc
from ogserver.app import Server, build
from ogserver.settings import Settings


@dataclass
class Running:
    server: Server
    address: str
    stub: pb_grpc.MappingStub  # plaintext, no API key

    @property
    def record_dir(self) -> Path:
        return self.server.registry.record_dir


def settings(tmp_path: Path) -> Settings:
    """The test server's settings, serving at once on a free local port."""
    result = Settings(address="127.0.0.1:0", record_dir=str(tmp_path / "recordings"), device="cpu",
                      torch_threads=2, warm_up=False)
    result.limits.max_image_pixels = 65536
    return result


@contextmanager
def serving(configured: Settings) -> Iterator[Running]:
    configured.validate()
    server = build(configured)
    address = f"127.0.0.1:{server.port}"
    channel = grpc.insecure_channel(address)
    try:
        yield Running(server, address, pb_grpc.MappingStub(channel))
    finally:
        channel.close()
        server.stop(0, 5)
