"""Checkpoints on their own (format, token hash, atomic replacement, damage refused) and resuming
sessions in-process from a record dir a 'crashed' registry left behind (the kill -9 test is
test_crash_resume.py)."""

from __future__ import annotations

import hashlib
import json
import os
import queue
import time
from pathlib import Path

import grpc
import pytest
import torch
from ogapi import recording
from ogapi.v1 import mapping_pb2 as pb
from ogclient.messages import frame_to_proto
from ogserver.access import tokens
from ogserver.access.callers import ANONYMOUS
from ogserver.api.validation import frame as validate_frame
from ogserver.errors import ServiceError
from ogserver.recording import checkpoint
from ogserver.recording.checkpoint import CheckpointError, Identity, Position
from ogserver.sessions.registry import Opened, Registry
from ogserver.sessions.resume import resume_all
from ogserver.settings import Settings

from ogmapping.config import OctreeConfig, resolve
from ogmapping.mapper import Mapper

from .held_mapper import flood_while_held, frame_messages
from .scene import FROZEN, PRESET, TINY, create_request, scene

TOKEN = "t" * 43


@pytest.fixture(scope="module")
def mapper() -> Mapper:
    """Two frames mapped (a keyframe, Adam moments): only read by the tests."""
    mapper = Mapper(resolve(PRESET, overrides=TINY))
    source = scene("0:4")
    for position in range(2):
        mapper.process(source.load(position))
    return mapper


def identity() -> Identity:
    return Identity("alice", tokens.TokenHash.of(TOKEN), pb.SessionConfig(session_id="a" * 32, label="kitchen"))


def test_a_checkpoint_holds_the_exact_map_and_who_the_session_is(tmp_path: Path, mapper: Mapper) -> None:
    path = tmp_path / f"{'a' * 32}{checkpoint.SUFFIX}"
    state = mapper.state(training_state=True)
    checkpoint.write_atomically(path, checkpoint.encode(identity(), Position(2, 7), state))
    saved = checkpoint.read(path)
    assert saved.identity.owner == "alice" and saved.identity.config.label == "kitchen"
    assert saved.identity.session_id == "a" * 32 and saved.position == Position(2, 7)
    assert saved.identity.token.matches(TOKEN) and not saved.identity.token.matches(TOKEN[:-1])
    assert TOKEN.encode() not in path.read_bytes()  # only the salted hash is stored
    assert state.tensors.keys() == saved.state.tensors.keys()
    assert any(name.startswith("training.keyframes.") for name in state.tensors)
    for name, tensor in state.tensors.items():  # float32 throughout: bit for bit, unlike a float16 snapshot
        torch.testing.assert_close(saved.state.tensors[name], tensor.cpu(), rtol=0, atol=0, equal_nan=True)
    assert [list(path.parent.iterdir())] == [[path]]  # no temporary file left


@pytest.mark.parametrize(("damage", "reason"), [
    (lambda data: data[: len(data) - 100], "damaged"),  # cut
    (lambda data: data[:-1] + bytes([data[-1] ^ 1]), "damaged"),  # one bit of a tensor
    (lambda data: data[:7], "not a checkpoint: snapshot is truncated"),
    (lambda data: data.replace(b"ogserver-checkpoint", b"ogserver-checkpoinx"), "is not 'ogserver-checkpoint'"),
])
def test_a_damaged_checkpoint_is_refused(mapper: Mapper, damage, reason: str) -> None:
    data = checkpoint.encode(identity(), Position(2, 7), mapper.state(training_state=True))
    with pytest.raises(CheckpointError, match=reason):
        checkpoint.decode(damage(data))


def test_a_plain_snapshot_is_not_a_checkpoint(mapper: Mapper) -> None:
    with pytest.raises(CheckpointError, match="without the checkpoint's metadata"):
        checkpoint.decode(mapper.snapshot())


def test_a_failed_write_leaves_the_previous_checkpoint(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                       mapper: Mapper) -> None:
    path = tmp_path / f"{'a' * 32}{checkpoint.SUFFIX}"
    checkpoint.write_atomically(path, checkpoint.encode(identity(), Position(1, 0), mapper.state()))
    before = path.read_bytes()

    def full_disk(descriptor: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", full_disk)
    with pytest.raises(OSError):
        checkpoint.write_atomically(path, checkpoint.encode(identity(), Position(2, 1), mapper.state()))
    assert path.read_bytes() == before and list(tmp_path.iterdir()) == [path]
    assert checkpoint.read(path).position == Position(1, 0)


# ---------------------------------------------------------------------------- resuming in-process


def settings(record_dir: Path, interval: int) -> Settings:
    return Settings(record_dir=str(record_dir), checkpoint_interval=interval)


def stream(opened: Opened, positions: range) -> list[pb.FrameAck]:
    sink: queue.SimpleQueue = queue.SimpleQueue()
    source = scene("0:8")
    for position in positions:
        message = frame_to_proto(source.load(position))
        assert opened.session.submit(validate_frame(message, 1 << 20, OctreeConfig()), message, sink)
    return [sink.get(timeout=60).ack for _ in positions]


def crash(opened: Opened) -> None:
    """The session's worker stops; its recording is left as a killed server leaves it (no clean end)."""
    opened.session.close()


def wait_mapped(registry: Registry, session_id: str, token: str, sequence: int) -> None:
    deadline = time.monotonic() + 60
    while registry.get(session_id, token).counters().mapped_sequence < sequence:
        assert time.monotonic() < deadline, "the resumed session did not map its recorded frames again"
        time.sleep(0.05)


def test_a_session_left_open_is_resumed_with_its_id_token_and_frames(tmp_path: Path) -> None:
    first = Registry(settings(tmp_path, interval=2), "cpu")
    opened = first.create(create_request(FROZEN, "kitchen"), "alice")
    acks = stream(opened, range(3))
    assert [ack.sequence for ack in acks] == [1, 2, 3]
    crash(opened)
    assert checkpoint.read(checkpoint.path_for(opened.session.recorder.path)).position == Position(2, 1)

    second = Registry(settings(tmp_path, interval=2), "cpu")
    resumed = resume_all(second)
    assert resumed.sessions == [opened.session.id] and not resumed.skipped
    with pytest.raises(ServiceError) as refusal:
        second.get(opened.session.id, "x" * 43)
    assert refusal.value.code == grpc.StatusCode.UNAUTHENTICATED
    wait_mapped(second, opened.session.id, opened.token, 3)  # frame 3, recorded after the checkpoint
    session = second.get(opened.session.id, opened.token)
    counters = session.counters()
    assert (counters.last_sequence, counters.last_index, counters.mapped, counters.received) == (3, 2, 1, 1)
    assert session.config.label == "kitchen" and second.sessions("alice") == [session]
    more = stream(Opened(session, opened.token), range(3, 5))
    assert [ack.sequence for ack in more] == [4, 5] and all(ack.accepted for ack in more)
    second.close(session)
    frames = [frame.index for _, frame in recording.load(session.recorder.path).frames]
    assert frames == [0, 1, 2, 3, 4] and recording.closed_cleanly(session.recorder.path)
    assert not checkpoint.path_for(session.recorder.path).exists()  # closed cleanly: nothing to resume
    assert resume_all(Registry(settings(tmp_path, interval=2), "cpu")).sessions == []


def test_sessions_that_cannot_be_resumed_are_skipped_and_left_as_they_are(tmp_path: Path) -> None:
    first = Registry(settings(tmp_path, interval=0), "cpu")
    damaged, missing, good = (first.create(create_request(FROZEN), ANONYMOUS) for _ in range(3))
    for opened in (damaged, missing, good):
        stream(opened, range(1))
        crash(opened)
    damaged_file = checkpoint.path_for(damaged.session.recorder.path)
    data = damaged_file.read_bytes()
    damaged_file.write_bytes(data[:-1] + bytes([data[-1] ^ 1]))
    checkpoint.path_for(missing.session.recorder.path).unlink()
    recordings = {opened.session.id: opened.session.recorder.path.read_bytes() for opened in (damaged, missing)}

    second = Registry(settings(tmp_path, interval=0), "cpu")
    resumed = resume_all(second)
    assert resumed.sessions == [good.session.id]
    assert set(resumed.skipped) == {f"{damaged.session.id}.mcap", f"{missing.session.id}.mcap"}
    assert "damaged" in resumed.skipped[f"{damaged.session.id}.mcap"]
    assert "cannot read" in resumed.skipped[f"{missing.session.id}.mcap"]
    for session_id, data in recordings.items():
        assert (tmp_path / f"{session_id}.mcap").read_bytes() == data
    wait_mapped(second, good.session.id, good.token, 1)


def test_a_recording_cut_inside_a_frame_resumes_from_the_frames_before_the_cut(tmp_path: Path) -> None:
    first = Registry(settings(tmp_path, interval=2), "cpu")
    opened = first.create(create_request(FROZEN), ANONYMOUS)
    path = opened.session.recorder.path
    stream(opened, range(2))
    two_frames = path.stat().st_size
    stream(opened, range(2, 3))
    crash(opened)
    data = path.read_bytes()
    path.write_bytes(data[: (two_frames + len(data)) // 2])  # the power went while frame 3 was being written

    second = Registry(settings(tmp_path, interval=2), "cpu")
    assert resume_all(second).sessions == [opened.session.id]
    session = second.get(opened.session.id, opened.token)
    assert (session.counters().last_sequence, session.counters().last_index) == (2, 1)
    assert [frame.index for _, frame in recording.load(path).frames] == [0, 1]
    assert [ack.sequence for ack in stream(Opened(session, opened.token), range(2, 4))] == [3, 4]
    second.close(session)
    assert [frame.index for _, frame in recording.load(path).frames] == [0, 1, 2, 3]


# ---------------------------------------------------------------------------- realtime sessions


def realtime_request() -> pb.CreateSessionRequest:
    request = create_request(FROZEN)
    request.realtime = True
    return request


def test_a_realtime_session_checkpoints_on_whichever_frame_it_maps(tmp_path: Path) -> None:
    """Its mapped frames' sequences fall anywhere between skipped ones: frame 6 is the first mapped
    four or more frames after the opening checkpoint, and no multiple of four is ever mapped."""
    registry = Registry(settings(tmp_path, interval=4), "cpu")
    opened = registry.create(realtime_request(), ANONYMOUS)
    sink: queue.SimpleQueue = queue.SimpleQueue()
    held = flood_while_held(opened.session, frame_messages(6), sink)
    held.release()  # frame 0 (sequence 1) is mapped, frames 1-4 were skipped, frame 5 (sequence 6) is taken up
    held.taken()
    held.release()
    acks = [sink.get(timeout=60).ack for _ in range(6)]
    assert sorted((ack.sequence, ack.skipped) for ack in acks) == [
        (1, False), (2, True), (3, True), (4, True), (5, True), (6, False)]
    deadline = time.monotonic() + 60
    while opened.session.checkpoints.written < 2:
        assert time.monotonic() < deadline, "no checkpoint after the frames it mapped"
        time.sleep(0.05)
    assert checkpoint.read(checkpoint.path_for(opened.session.recording)).position == Position(6, 5)
    registry.close(opened.session)


def test_a_resumed_realtime_session_skips_what_it_skipped_and_answers_a_new_frame(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    first = Registry(settings(tmp_path, interval=0), "cpu")
    opened = first.create(realtime_request(), ANONYMOUS)
    sink: queue.SimpleQueue = queue.SimpleQueue()
    messages = frame_messages(31)
    held = flood_while_held(opened.session, messages, sink)
    held.release()
    held.taken()
    held.release()
    acks = [sink.get(timeout=60).ack for _ in messages]
    assert sum(ack.skipped for ack in acks) == 29
    crash(opened)  # the last frame's ack is lost with the writer's buffer: that frame is mapped again

    def slow(self: Mapper, frame, budget=None):
        time.sleep(0.25)  # 31 frames mapped again would take 8 s or more
        return mapping(self, frame, budget)

    mapping = Mapper.process
    monkeypatch.setattr(Mapper, "process", slow)
    second = Registry(settings(tmp_path, interval=0), "cpu")
    assert resume_all(second).sessions == [opened.session.id]
    session = second.get(opened.session.id, opened.token)
    assert (session.counters().last_sequence, session.counters().last_index) == (31, 30)
    started = time.monotonic()
    more = stream(Opened(session, opened.token), range(1))
    answered = time.monotonic() - started
    counters = session.counters()
    assert [ack.sequence for ack in more] == [32] and not more[0].skipped
    assert (counters.mapped, counters.skipped) == (3, 0), "frames the live session skipped were mapped"
    assert answered < 4.0, f"the new frame waited {answered:.1f} s behind recorded frames"
    second.close(session)


# ---------------------------------------------------------------------------- what resume trusts


def test_a_checkpoint_whose_owner_was_edited_is_not_resumed(tmp_path: Path) -> None:
    first = Registry(settings(tmp_path, interval=0), "cpu")
    opened = first.create(create_request(FROZEN), "alice")
    stream(opened, range(1))
    crash(opened)
    path = checkpoint.path_for(opened.session.recorder.path)
    data = path.read_bytes()
    edited = data.replace(b'\\"owner\\": \\"alice\\"', b'\\"owner\\": \\"mallo\\"')
    assert edited != data
    path.write_bytes(edited)

    second = Registry(settings(tmp_path, interval=0), "cpu")
    resumed = resume_all(second)
    assert resumed.sessions == [] and "edited" in resumed.skipped[f"{opened.session.id}.mcap"]
    assert second.sessions() == [] and path.read_bytes() == edited


def test_a_checkpoint_from_before_the_digest_covered_its_identity_is_refused(mapper: Mapper) -> None:
    header, payload = checkpoint._split(checkpoint.encode(identity(), Position(2, 7), mapper.state()))
    metadata = header["__metadata__"]
    entry = json.loads(metadata[checkpoint.KEY])
    entry["version"] = 1
    metadata[checkpoint.KEY] = json.dumps(entry)
    del metadata[checkpoint.DIGEST_KEY]
    metadata["payload_sha256"] = hashlib.sha256(payload).hexdigest()
    text = json.dumps(header).encode()
    with pytest.raises(CheckpointError, match="version 1, from an older server"):
        checkpoint.decode(len(text).to_bytes(8, "little") + text + payload)


def test_another_sessions_recording_under_this_ones_name_is_not_resumed(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    first = Registry(settings(tmp_path, interval=0), "cpu")
    mine, theirs = (first.create(create_request(FROZEN), "alice") for _ in range(2))
    stream(mine, range(1))
    stream(theirs, range(3))
    crash(mine)
    crash(theirs)
    copied = theirs.session.recorder.path.read_bytes()
    mine.session.recorder.path.write_bytes(copied)  # a copy mistake, or two nodes' shared storage mixed up

    second = Registry(settings(tmp_path, interval=0), "cpu")
    with caplog.at_level("ERROR"):
        resumed = resume_all(second)
    assert resumed.sessions == [theirs.session.id]
    reason = resumed.skipped[f"{mine.session.id}.mcap"]
    assert f"recording of session {theirs.session.id}, not of {mine.session.id}" in reason
    assert f"session of {mine.session.id}.mcap not resumed" in caplog.text
    assert mine.session.recorder.path.read_bytes() == copied
    second.close(second.get(theirs.session.id, theirs.token))
