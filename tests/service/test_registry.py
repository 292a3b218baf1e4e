"""The registry without gRPC: sessions opened and closed on a disk that fills up, and a record dir
the server cannot use."""

from __future__ import annotations

import queue
from pathlib import Path

import grpc
import pytest
from mcap.reader import make_reader
from ogclient.messages import frame_to_proto
from ogserver.access.callers import ANONYMOUS
from ogserver.api.validation import frame as validate_frame
from ogserver.app import build
from ogserver.errors import ServiceError
from ogserver.sessions.registry import Opened, Registry
from ogserver.settings import Settings

from ogmapping.config import OctreeConfig

from .conftest import FullDisk
from .scene import FROZEN, create_request, scene


def registry(tmp_path: Path) -> Registry:
    return Registry(Settings(record_dir=str(tmp_path), final_snapshots=True), "cpu")


def map_frames(registry: Registry, count: int) -> Opened:
    opened = registry.create(create_request(FROZEN), ANONYMOUS)
    session = opened.session
    sink: queue.SimpleQueue = queue.SimpleQueue()
    frames = scene("0:4")
    for position in range(count):
        message = frame_to_proto(frames.load(position))
        assert session.submit(validate_frame(message, 1 << 20, OctreeConfig()), message, sink)
    assert all(sink.get(timeout=60).ack.accepted for _ in range(count))
    return opened


def test_create_on_a_full_disk_is_refused_and_leaves_no_file(tmp_path: Path, full_disk: FullDisk) -> None:
    sessions = registry(tmp_path)
    full_disk.free = 0
    with pytest.raises(ServiceError) as refusal:
        sessions.create(create_request(FROZEN), ANONYMOUS)
    assert refusal.value.code == grpc.StatusCode.RESOURCE_EXHAUSTED and str(tmp_path) not in refusal.value.message
    assert list(tmp_path.iterdir()) == [] and sessions.sessions() == []
    full_disk.free = None
    sessions.close(sessions.create(create_request(FROZEN), ANONYMOUS).session)  # the refused one took no slot


def test_close_on_a_full_disk_keeps_the_session_until_it_can_finish(tmp_path: Path, full_disk: FullDisk) -> None:
    sessions = registry(tmp_path)
    opened = map_frames(sessions, 2)
    session = opened.session
    full_disk.free = 0
    with pytest.raises(ServiceError) as refusal:
        sessions.close(session)
    assert refusal.value.code == grpc.StatusCode.RESOURCE_EXHAUSTED and "still open" in refusal.value.message
    assert sessions.get(session.id, opened.token) is session and session.snapshot()  # its map is still there
    full_disk.free = None
    closed = sessions.close(session)
    assert closed.stats.frames == 2 and closed.snapshot is not None and closed.snapshot.exists()
    with open(closed.recording, "rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None and summary.statistics.message_count > 0
    with pytest.raises(ServiceError) as gone:
        sessions.get(session.id, opened.token)
    assert gone.value.code == grpc.StatusCode.NOT_FOUND


def test_an_unusable_record_dir_stops_the_server_before_it_serves(tmp_path: Path) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    settings = Settings(address="127.0.0.1:0", record_dir=str(blocker / "recordings"), device="cpu", warm_up=False)
    with pytest.raises(ValueError, match=r"record dir .* is not writable"):
        server = build(settings)
        server.stop(0, 0)  # only reached if build did not refuse
