"""Recordings without a server: layout, Foxglove channels, files cut off mid-write, damaged files, a full disk."""

from __future__ import annotations

import math
import time
from pathlib import Path

import grpc
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from ogapi import recording as layout
from ogapi.convert import FrameEncoding
from ogapi.v1 import mapping_pb2 as pb
from ogclient.messages import frame_to_proto
from ogserver.api.validation import MAX_TIMESTAMP_SECONDS
from ogserver.api.validation import frame as validate_frame
from ogserver.recording.disk import StorageError
from ogserver.recording.recorder import PROVISIONAL_END, Recorder, frame_record

from ogmapping.config import OctreeConfig

from .conftest import FullDisk
from .scene import scene

FOXGLOVE = {
    layout.TOPIC_COLOR: "foxglove.CompressedImage",
    layout.TOPIC_DEPTH: "foxglove.CompressedImage",
    layout.TOPIC_CALIBRATION: "foxglove.CameraCalibration",
    layout.TOPIC_TRANSFORM: "foxglove.FrameTransform",
}


def write_frames(recorder: Recorder, positions: range, encoding: FrameEncoding | None = None) -> None:
    frames = scene("0:4")
    for position in positions:
        message = frame_to_proto(frames.load(position), encoding or FrameEncoding())
        recorder.write_frame(frame_record(message, validate_frame(message, 1 << 20, OctreeConfig()), time.time_ns()))
        recorder.write_ack(pb.FrameAck(index=position, accepted=True, sequence=position + 1))


def write(path: Path, count: int, encoding: FrameEncoding | None = None, close: bool = True) -> Recorder:
    recorder = Recorder(path, pb.SessionConfig(session_id="0" * 32, preset="sparse"))
    write_frames(recorder, range(count), encoding)
    if close:
        recorder.close(pb.Stats(frames=count))
    return recorder


def middle_of_largest_chunk(path: Path) -> int:
    """A byte inside the largest chunk's records, whatever the file's other records add around it."""
    with open(path, "rb") as stream:
        chunks = make_reader(stream).get_summary().chunk_indexes
    largest = max(chunks, key=lambda chunk: chunk.chunk_length)
    return largest.chunk_start_offset + largest.chunk_length // 2


def standard_read(path: Path) -> tuple[bool, dict[str, int]]:
    """What mcap's own ``make_reader`` sees: whether there is a summary, and messages per topic."""
    with open(path, "rb") as stream:
        reader = make_reader(stream)
        has_summary = reader.get_summary() is not None
        counts: dict[str, int] = {}
        for _, channel, _ in reader.iter_messages():
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    return has_summary, counts


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
        recorder.write_frame(frame_record(message, validate_frame(message, 1 << 20, OctreeConfig()), arrival_ns))
    recorder.close()
    with open(path, "rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        images = [(message.publish_time, decoded.timestamp.ToNanoseconds())
                  for _, _, message, decoded in reader.iter_decoded_messages(topics=[layout.TOPIC_COLOR])]
    assert images == [(0, 0), (arrival_ns, arrival_ns)]
    recorded = layout.load(path)
    assert [frame.HasField("timestamp") for _, frame in recorded.frames] == [True, False]


def test_a_recording_cut_between_frames_opens_in_the_standard_reader(tmp_path: Path) -> None:
    """A crash between two frames leaves a file ending in the provisional end: a complete MCAP."""
    path = tmp_path / "session.mcap"
    recorder = write(path, 3, close=False)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes())
    recorder.close()
    assert cut.read_bytes().endswith(PROVISIONAL_END)
    has_summary, counts = standard_read(cut)
    assert not has_summary
    assert counts[layout.TOPIC_FRAMES] == 3 and counts[layout.TOPIC_ACKS] == 2  # the last ack waits for a flush


def test_repair_gives_a_recording_cut_inside_a_record_its_summary(tmp_path: Path) -> None:
    path = tmp_path / "session.mcap"
    recorder = write(path, 2, close=False)
    two_frames = path.stat().st_size
    write_frames(recorder, range(2, 3))
    data = path.read_bytes()
    recorder.close()
    cut, repaired = tmp_path / "cut.mcap", tmp_path / "repaired.mcap"
    cut.write_bytes(data[: (two_frames + len(data)) // 2])  # inside the third frame's chunk
    with pytest.raises(Exception):  # noqa: B017 - whatever mcap raises for a file without its end
        standard_read(cut)
    count = layout.repair(cut, repaired)
    has_summary, counts = standard_read(repaired)
    assert has_summary and counts[layout.TOPIC_SESSION] == 1 and counts[layout.TOPIC_FRAMES] == 2
    assert count == sum(counts.values())
    original = [(m.topic, m.log_time_ns, m.data) for m in layout.read_messages(cut)]
    assert [(m.topic, m.log_time_ns, m.data) for m in layout.read_messages(repaired)] == original


@pytest.mark.parametrize("damage", ["not mcap", "flipped byte"])
def test_a_damaged_recording_is_a_recording_error(tmp_path: Path, damage: str) -> None:
    path = tmp_path / "session.mcap"
    write(path, 2)
    data = bytearray(path.read_bytes())
    if damage == "not mcap":
        data[:8] = b"NOT MCAP"
    else:
        data[middle_of_largest_chunk(path)] ^= 0xFF  # its CRC no longer matches
    path.write_bytes(bytes(data))
    with pytest.raises(layout.RecordingError, match="not a readable recording"):
        layout.load(path)
    with pytest.raises(layout.RecordingError):
        layout.repair(path, tmp_path / "repaired.mcap")
    assert not (tmp_path / "repaired.mcap").exists()


def test_the_largest_timestamp_validation_accepts_is_recorded(tmp_path: Path) -> None:
    path = tmp_path / "session.mcap"
    recorder = Recorder(path, pb.SessionConfig(session_id="0" * 32, preset="sparse"))
    message = frame_to_proto(scene("0:1").load(0))
    message.timestamp = math.nextafter(MAX_TIMESTAMP_SECONDS, 0.0)
    recorder.write_frame(frame_record(message, validate_frame(message, 1 << 20, OctreeConfig()), time.time_ns()))
    recorder.close()
    with open(path, "rb") as stream:
        times = [record.publish_time for _, _, record in make_reader(stream).iter_messages([layout.TOPIC_COLOR])]
    assert times == [round(message.timestamp * 1e9)] and times[0] < 2**64


def test_a_full_disk_stops_the_recording_at_the_last_whole_frame(tmp_path: Path, full_disk: FullDisk) -> None:
    path = tmp_path / "session.mcap"
    recorder = write(path, 2, close=False)
    full_disk.free = 1000  # part of the next frame fits
    with pytest.raises(StorageError) as failure:
        write_frames(recorder, range(2, 3))
    assert failure.value.code == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert "No space left on device" in failure.value.message and str(tmp_path) not in failure.value.message
    assert recorder.failure is failure.value
    with pytest.raises(StorageError):  # for good, even with space again
        full_disk.free = None
        write_frames(recorder, range(3, 4))
    has_summary, counts = standard_read(path)  # cut back to the last whole frame, provisional end included
    assert not has_summary and counts[layout.TOPIC_FRAMES] == 2


def test_closing_a_failed_recording_rewrites_it_with_a_summary_once_there_is_space(
    tmp_path: Path, full_disk: FullDisk
) -> None:
    path = tmp_path / "session.mcap"
    recorder = write(path, 2, close=False)
    full_disk.free = 0
    with pytest.raises(StorageError):
        write_frames(recorder, range(2, 3))
    with pytest.raises(StorageError) as failure:
        recorder.close(pb.Stats(frames=2))
    assert failure.value.code == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert sorted(p.name for p in tmp_path.iterdir()) == ["session.mcap"]  # no partial rewrite left
    full_disk.free = None
    recorder.close(pb.Stats(frames=2))
    has_summary, counts = standard_read(path)
    assert has_summary and counts[layout.TOPIC_FRAMES] == 2 and counts[layout.TOPIC_STATS] == 1
    assert layout.load(path).stats.frames == 2


def test_a_recording_that_cannot_start_leaves_no_file(tmp_path: Path, full_disk: FullDisk) -> None:
    full_disk.free = 10
    with pytest.raises(StorageError) as failure:
        Recorder(tmp_path / "session.mcap", pb.SessionConfig(session_id="0" * 32, preset="sparse"))
    assert failure.value.code == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert list(tmp_path.iterdir()) == []
