"""Recordings without a server: layout, Foxglove channels, and reading a file cut off mid-write."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from ogapi import recording as layout
from ogapi.convert import FrameEncoding
from ogapi.v1 import mapping_pb2 as pb
from ogclient.messages import frame_to_proto
from ogserver.recorder import Recorder, quaternion
from ogserver.validation import frame as validate_frame

from ogmapping.config import OctreeConfig

from .scene import scene

FOXGLOVE = {
    layout.TOPIC_COLOR: "foxglove.CompressedImage",
    layout.TOPIC_DEPTH: "foxglove.CompressedImage",
    layout.TOPIC_CALIBRATION: "foxglove.CameraCalibration",
    layout.TOPIC_TRANSFORM: "foxglove.FrameTransform",
}


def write(path: Path, count: int, encoding: FrameEncoding | None = None, close: bool = True) -> Recorder:
    encoding = encoding or FrameEncoding()
    recorder = Recorder(path, pb.SessionConfig(session_id="0" * 32, preset="sparse"))
    frames = scene("0:4")
    for position in range(count):
        message = frame_to_proto(frames.load(position), encoding)
        recorder.write_frame(message, validate_frame(message, 1 << 20, OctreeConfig()), time.time_ns())
        recorder.write_ack(pb.FrameAck(index=position, accepted=True, sequence=position + 1))
    if close:
        recorder.close(pb.Stats(frames=count))
    return recorder


@pytest.mark.parametrize("encoding", [FrameEncoding(), FrameEncoding(color=pb.COLOR_RAW_RGB8, depth=pb.DEPTH_RAW_F32)])
def test_clean_recording_has_every_channel(tmp_path: Path, encoding: FrameEncoding) -> None:
    path = tmp_path / "session.mcap"
    write(path, 3, encoding)
    with open(path, "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        counts = {channel.topic: summary.statistics.channel_message_counts[cid]
                  for cid, channel in summary.channels.items()}
        schemas = {channel.topic: summary.schemas[channel.schema_id].name for channel in summary.channels.values()}
        decoded = {topic: [] for topic in FOXGLOVE}
        for _, channel, _, message in reader.iter_decoded_messages(topics=list(FOXGLOVE)):
            decoded[channel.topic].append(message)
    assert counts == {layout.TOPIC_SESSION: 1, layout.TOPIC_FRAMES: 3, layout.TOPIC_ACKS: 3, layout.TOPIC_STATS: 1,
                      **dict.fromkeys(FOXGLOVE, 3)}
    assert {topic: schemas[topic] for topic in FOXGLOVE} == FOXGLOVE
    assert all(image.format == "png" for image in decoded[layout.TOPIC_COLOR])
    assert decoded[layout.TOPIC_TRANSFORM][0].parent_frame_id == layout.WORLD_FRAME
    recorded = layout.load(path)
    assert recorded.config.preset == "sparse" and recorded.stats.frames == 3
    assert [frame.index for _, frame in recorded.frames] == [0, 1, 2]


def test_cut_off_recording_reads_up_to_the_last_frame(tmp_path: Path) -> None:
    path = tmp_path / "session.mcap"
    recorder = write(path, 3, close=False)  # never closed: no summary, as after a crash
    data = path.read_bytes()
    recorder.close()
    for cut in (len(data), len(data) - 7):
        path.write_bytes(data[:cut])
        recorded = layout.load(path)
        assert recorded.config is not None
        assert len(recorded.frames) >= (3 if cut == len(data) else 2)


def test_quaternion_matches_rotation() -> None:
    angle = 0.7
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    x, y, z, w = quaternion(rotation)
    np.testing.assert_allclose([x, y, z, w], [0, 0, np.sin(angle / 2), np.cos(angle / 2)], atol=1e-12)
    for flip in (np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])):
        q = np.array(quaternion(flip))
        assert np.isclose(np.linalg.norm(q), 1.0) and np.isclose(np.abs(q[:3]).max(), 1.0)


def test_a_zero_timestamp_is_kept_and_a_missing_one_becomes_the_arrival_time(tmp_path: Path) -> None:
    path = tmp_path / "session.mcap"
    recorder = Recorder(path, pb.SessionConfig(session_id="0" * 32, preset="sparse"))
    frames = scene("0:4")
    arrival_ns = 1_700_000_000_000_000_000
    stamped = frame_to_proto(frames.load(0))
    stamped.timestamp = 0.0  # a clock that starts at zero
    unstamped = frame_to_proto(frames.load(1))
    unstamped.ClearField("timestamp")
    for message in (stamped, unstamped):
        recorder.write_frame(message, validate_frame(message, 1 << 20, OctreeConfig()), arrival_ns)
    recorder.close()
    with open(path, "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        images = [(message.publish_time, decoded.timestamp.ToNanoseconds())
                  for _, _, message, decoded in reader.iter_decoded_messages(topics=[layout.TOPIC_COLOR])]
    assert images == [(0, 0), (arrival_ns, arrival_ns)]
    recorded = layout.load(path)
    assert [frame.HasField("timestamp") for _, frame in recorded.frames] == [True, False]
