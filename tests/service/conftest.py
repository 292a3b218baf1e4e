"""A server for the integration tests ($OGMAP_SERVER when set: the container test, with its record dir
mounted at $OGMAP_RECORD_DIR; else a subprocess), and a disk that fills up."""

from __future__ import annotations

import errno
import io
import os
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import grpc
import pytest
from ogapi.v1 import mapping_pb2_grpc as pb_grpc
from ogclient.connection import connect
from ogclient.local_server import LocalServer
from ogserver.recording import recorder

from .scene import TEST_SERVER_CONFIG


@dataclass
class ServerHandle:
    address: str
    channel: grpc.Channel
    stub: pb_grpc.MappingStub
    local: LocalServer | None

    def recorded(self, name: str) -> Path | None:
        """A file the server names (a recording, a final snapshot) where this process sees it; None if it does not."""
        record_dir = self.local.record_dir if self.local else os.environ.get("OGMAP_RECORD_DIR")
        path = Path(record_dir) / name if record_dir else None
        return path if path is not None and path.exists() else None


@pytest.fixture(scope="session", autouse=True)
def compiled_kernels() -> None:
    """Compile the engine's kernels once, before the first test's clock starts: a fresh checkout compiles
    them on first use (about 45 s on a 2-core machine), which would otherwise land inside whichever test maps
    the first frame in this process, and past its deadlines."""
    from ogmapping.warmup import warm_up

    warm_up("cpu")


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


class FullDisk:
    """The recorder's files on a disk with ``free`` bytes left (None: unlimited), like a disk filling
    up: a write gets what still fits, the next one ENOSPC. Overwriting costs nothing, growing a file
    costs free bytes, and bytes a truncate frees are not given back."""

    def __init__(self) -> None:
        self.free: int | None = None

    def open(self, path: str | Path, mode: str = "r", buffering: int = -1) -> io.RawIOBase | io.BufferedWriter:
        assert mode == "wb", "the recorder only writes new files"
        disk = self

        class FillingFile(io.FileIO):
            def write(self, data: bytes) -> int:
                if disk.free is None:
                    return super().write(data)
                position, size = self.tell(), os.fstat(self.fileno()).st_size
                fits = max(0, size - position) + disk.free
                if fits == 0:
                    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
                written = super().write(memoryview(data)[:fits])
                disk.free -= max(0, position + written - size)
                return written

        file = FillingFile(path, "wb")
        return file if buffering == 0 else io.BufferedWriter(file)


@pytest.fixture
def full_disk(monkeypatch: pytest.MonkeyPatch) -> FullDisk:
    """Every recording opened from now on is written through a ``FullDisk`` (unlimited until told)."""
    disk = FullDisk()
    monkeypatch.setattr(recorder, "open", disk.open, raising=False)
    return disk
