"""Shared storage at an fsspec URL (memory:// and file://, no Ray): a session's checkpoint and recording
are uploaded as it maps, a node that never saw the session fetches them and resumes it, and closing it
publishes the finished recording and removes what only a resume needed."""

from __future__ import annotations

import uuid
from pathlib import Path

import pytest
from ogapi import recording as layout
from ogserver.recording.checkpoint import SUFFIX
from ogserver.recording.shared_store import Part, SharedStore
from ogserver.sessions.registry import Registry
from ogserver.settings import Settings

from .test_registry import map_frames

fsspec = pytest.importorskip("fsspec", reason="shared storage needs fsspec (the 'cluster' extra)")


@pytest.fixture(params=["memory", "file"])
def url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    if request.param == "memory":
        return f"memory://og-{uuid.uuid4().hex}/recordings"
    return (tmp_path / "bucket" / "recordings").as_uri()


def node(scratch: Path, url: str) -> Registry:
    """One node's registry: its own scratch record dir, the shared store at ``url``."""
    return Registry(Settings(record_dir=str(scratch), shared_storage=url, cluster="auto", checkpoint_interval=2,
                             final_snapshots=True), "cpu")


def frames_in(data: bytes, where: Path) -> int:
    where.write_bytes(data)
    return sum(1 for _ in layout.read_messages(where, {layout.TOPIC_FRAMES}))


def test_a_session_moves_to_a_node_that_never_saw_it_through_the_store(tmp_path: Path, url: str) -> None:
    first = node(tmp_path / "node-a", url)
    opened = map_frames(first, 3)  # checkpoints at frame 2; frame 3 is in the recording only
    session_id = opened.session.id
    store = SharedStore(url)
    assert store.get(f"{session_id}{SUFFIX}") is not None
    assert frames_in(store.recording(f"{session_id}.mcap").assemble(), tmp_path / "assembled.mcap") == 3
    # node-a is lost without closing anything: node-b starts from an empty scratch dir
    second = node(tmp_path / "node-b", url)
    assert second.store is not None and second.store.fetch(session_id, second.record_dir)
    resumed = second.resume(second.record_dir / f"{session_id}.mcap")
    assert resumed.id == session_id and second.get(session_id, opened.token) is resumed  # same id and token
    assert resumed.counters().last_sequence == 3
    folder = store.recording(f"{session_id}.mcap").folder
    generations = {part.generation for entry in store.fs.ls(folder, detail=False)
                   if (part := Part.parse(entry.rsplit("/", 1)[-1]))}
    assert generations == {1}, "the resumed recording is a new generation of parts, the old one removed"
    closed = second.close(resumed)
    assert closed.stats.last_sequence == 3
    published = store.get(f"{session_id}.mcap")
    assert published is not None and frames_in(published, tmp_path / "published.mcap") == 3
    assert store.get(f"{session_id}.safetensors") is not None  # the final snapshot
    assert store.get(f"{session_id}{SUFFIX}") is None, "a closed session left its checkpoint"
    assert not store.fs.exists(store.path(f"{session_id}.mcap.parts"))


def test_a_part_cut_short_ends_the_assembled_recording_before_it(tmp_path: Path, url: str) -> None:
    store = SharedStore(url)
    parts = store.recording("cut.mcap")
    map_frames(node(tmp_path / "whole", url), 2)  # a real recording, to cut a copy of
    real = next(name for name in store.fs.ls(store.root, detail=False) if name.endswith(".mcap.parts"))
    names = sorted(entry.rsplit("/", 1)[-1] for entry in store.fs.ls(real, detail=False))
    store.fs.makedirs(parts.folder, exist_ok=True)
    for name in names:
        store.fs.pipe_file(f"{parts.folder}/{name}", store.fs.cat_file(f"{real}/{name}"))
    whole = frames_in(parts.assemble(), tmp_path / "whole.mcap")
    last = Part.parse(names[-1])
    assert last is not None and whole == 2
    store.fs.pipe_file(f"{parts.folder}/{last.name}", store.fs.cat_file(f"{real}/{last.name}")[:-3])
    assert frames_in(parts.assemble(), tmp_path / "cut.mcap") == 1  # the last frame's part is ignored
