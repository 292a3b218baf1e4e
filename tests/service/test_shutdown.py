"""The server process ending: SIGKILL leaves readable recordings, SIGTERM finishes them and the maps,
within a deadline even while a frame is still being mapped."""

from __future__ import annotations

import time
from pathlib import Path

from mcap.reader import make_reader
from ogapi import recording
from ogclient.connection import SessionRef, connect
from ogclient.local_server import LocalServer
from ogclient.streaming import stream_frames
from ogserver.api.validation import frame as validate_frame

from ogmapping.config import OctreeConfig
from ogmapping.mapper import Mapper

from .conftest import start_local
from .scene import FROZEN, LIMITS, create_request, messages, scene

# The first frame would map for minutes on a CPU (500 is the default config_bounds.max_iterations);
# closing cancels it between two iterations, and --stop-timeout bounds the wait even if it did not.
SLOW = {**FROZEN, "keyframes.first_iterations": "500"}
GRACE, STOP_TIMEOUT = 1.0, 2.0

FOXGLOVE_TOPICS = (recording.TOPIC_COLOR, recording.TOPIC_DEPTH, recording.TOPIC_CALIBRATION,
                   recording.TOPIC_TRANSFORM)


def map_a_little(server: LocalServer, frames: str) -> tuple[Path, SessionRef, int]:
    channel, stub = connect(server.address, timeout=60)
    with channel:
        credentials = stub.CreateSession(create_request(FROZEN, "shutdown"))
        session = SessionRef.from_credentials(credentials)
        result = stream_frames(stub, session, messages(scene(frames)), progress=False)
    assert all(ack.accepted for ack in result.acks)
    return server.record_dir / credentials.recording, session, result.acks[-1].anchors


def test_sigkill_leaves_every_frame_readable(tmp_path: Path) -> None:
    server = start_local(tmp_path / "recordings")
    try:
        path, _, _ = map_a_little(server, "0:4")
        server.kill()
    finally:
        server.stop()
    topics: dict[str, int] = {}
    for message in recording.read_messages(path):
        topics[message.topic] = topics.get(message.topic, 0) + 1
    assert topics[recording.TOPIC_FRAMES] == 4
    assert all(topics[topic] == 4 for topic in FOXGLOVE_TOPICS)
    assert recording.TOPIC_STATS not in topics  # never closed
    recorded = recording.load(path)
    assert recorded.config.preset == "sparse-fast"
    for _, message in recorded.frames:  # what a replay would send is intact
        validate_frame(message, LIMITS["max_image_pixels"], OctreeConfig())


def test_sigterm_finishes_recordings_and_writes_final_snapshots(tmp_path: Path) -> None:
    server = start_local(tmp_path / "recordings", "--final-snapshots")
    try:
        path, session, anchors = map_a_little(server, "0:3")
    finally:
        code = server.stop()
    assert code == 0
    assert any(line.startswith(f"closed session {session.session_id}") for line in server.output)
    with open(path, "rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    stats_channel = next(cid for cid, channel in summary.channels.items() if channel.topic == recording.TOPIC_STATS)
    assert summary.statistics.channel_message_counts[stats_channel] == 1
    snapshot = path.with_suffix(".safetensors")
    assert Mapper.restore(snapshot.read_bytes(), "cpu").stats().anchors == anchors


def wait_for_recorded_frame(path: Path, timeout: float = 60.0) -> None:
    """The worker records a frame as it takes it up, so then it is being mapped."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if any(message.topic == recording.TOPIC_FRAMES for message in recording.read_messages(path)):
                return
        except recording.RecordingError:  # read while the writer overwrites the file's end
            pass
        time.sleep(0.2)
    raise AssertionError("the frame was never taken up")


def test_sigterm_during_a_long_frame_exits_within_the_deadline(tmp_path: Path) -> None:
    server = start_local(tmp_path / "recordings", "--no-warm-up", "--grace", str(GRACE),
                         "--stop-timeout", str(STOP_TIMEOUT))
    channel, stub = connect(server.address, timeout=60)
    try:
        credentials = stub.CreateSession(create_request(SLOW, "slow"))
        session = SessionRef.from_credentials(credentials)
        responses = stub.StreamFrames(iter(messages(scene("0:1"))), metadata=session.stream_metadata())
        recorded = server.record_dir / credentials.recording
        wait_for_recorded_frame(recorded)
        start = time.monotonic()
        code = server.stop()
        elapsed = time.monotonic() - start
        responses.cancel()
    finally:
        channel.close()
        server.stop()
    assert code == 0 and elapsed < GRACE + 2 * STOP_TIMEOUT + 10, (code, elapsed)
    with open(recorded, "rb") as stream:
        summary = make_reader(stream).get_summary()
    counts = {channel.topic: summary.statistics.channel_message_counts[cid]
              for cid, channel in summary.channels.items()}
    assert counts[recording.TOPIC_FRAMES] == counts[recording.TOPIC_STATS] == 1
