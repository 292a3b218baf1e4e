"""The layout of a session recording (MCAP, protobuf), a reader that survives a crashed writer,
and a repair that gives a cut recording the summary and index a clean close appends.

The server flushes a complete MCAP chunk before it maps each frame and ends the file after it with
a provisional end (a Footer without a summary) that the next flush overwrites, so a file cut by a
crash between two flushes is a complete MCAP that any reader opens. ``read_messages`` also reads a
file cut inside a record, up to that record, and ``repair`` rewrites either kind with a summary.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import zstandard
from google.protobuf.message import DecodeError
from mcap.exceptions import EndOfFile, McapError
from mcap.records import Channel, Header, Message, Schema
from mcap.writer import CompressionType, Writer

from ogapi import mcap_records
from ogapi.v1 import mapping_pb2 as pb

TOPIC_SESSION = "/ogmap/session"  # ogapi.v1.SessionConfig, first message
TOPIC_FRAMES = "/ogmap/frames"  # ogapi.v1.Frame, every frame the session mapped (or tried to), as received
TOPIC_ACKS = "/ogmap/acks"  # ogapi.v1.FrameAck, one per recorded frame once it is mapped (or skipped)
TOPIC_STATS = "/ogmap/stats"  # ogapi.v1.Stats, at close
# ogapi.v1.PoseCorrections, each CorrectPoses batch the map took, after the frame it was applied after
TOPIC_CORRECTIONS = "/ogmap/pose_corrections"
TOPIC_COLOR = "/camera/color"  # foxglove.CompressedImage
TOPIC_DEPTH = "/camera/depth"  # foxglove.CompressedImage, 16-bit PNG
TOPIC_CALIBRATION = "/camera/calibration"  # foxglove.CameraCalibration
TOPIC_TRANSFORM = "/tf"  # foxglove.FrameTransform, world -> camera
# foxglove.FrameTransform, world -> camera_refined: with poses.refine, the refined pose of each mapped
# frame (its ack's pose_correction.refined_c2w), written with the ack
TOPIC_REFINED_TRANSFORM = "/tf_refined"
TOPIC_RENDER = "/ogmap/render"  # foxglove.CompressedImage, the map rendered from a keyframe's pose (JPEG)
TOPIC_MAP = "/ogmap/map"  # foxglove.PointCloud, the map's Gaussians (centres, RGBA) as of that keyframe
WORLD_FRAME = "world"
CAMERA_FRAME = "camera"
REFINED_CAMERA_FRAME = "camera_refined"


class RecordingError(ValueError):
    """A file that is not a recording, or one damaged before its end (a cut end is not damage)."""


@dataclass(frozen=True)
class RecordedMessage:
    topic: str
    schema: str
    log_time_ns: int
    data: bytes


def _records(path: str | Path) -> Iterator[Header | Schema | Channel | Message]:
    """The records in file order, chunks opened and their CRCs checked; a file that ends inside a
    record (a crashed writer) just ends early. Lengths and sizes beyond the file or ``MAX_CHUNK_BYTES``
    are refused before anything of that size is allocated."""
    with open(path, "rb") as stream:
        records = mcap_records.records(stream)
        while True:
            try:
                record = next(records)
            except StopIteration:
                return
            except (EndOfFile, struct.error):  # the file ends inside a record
                return
            except (McapError, ValueError, zstandard.ZstdError) as error:
                raise RecordingError(f"{path} is not a readable recording: {error}") from None
            if isinstance(record, Header | Schema | Channel | Message):
                yield record


def _unknown_channel(path: str | Path, message: Message) -> RecordingError:
    return RecordingError(f"{path} is not a readable recording: a message on unknown channel {message.channel_id}")


def read_messages(path: str | Path, topics: set[str] | None = None) -> Iterator[RecordedMessage]:
    """Messages in file order, up to where the file ends; ``RecordingError`` where it is damaged."""
    schemas: dict[int, str] = {}
    channels: dict[int, tuple[str, str]] = {}
    for record in _records(path):
        if isinstance(record, Schema):
            schemas[record.id] = record.name
        elif isinstance(record, Channel):
            channels[record.id] = (record.topic, schemas.get(record.schema_id, ""))
        elif isinstance(record, Message):
            if record.channel_id not in channels:
                raise _unknown_channel(path, record)
            topic, schema = channels[record.channel_id]
            if topics is None or topic in topics:
                yield RecordedMessage(topic, schema, record.log_time, record.data)


@dataclass(frozen=True)
class Copied:
    messages: int
    channels: dict[str, int]  # the writer's channel id for each topic copied


def copy_records(source: str | Path, writer: Writer) -> Copied:
    """Start ``writer`` with the source's header, then add the source's schemas, channels and
    messages in file order (those a summary repeats, once)."""
    started = False
    schemas: dict[int, int] = {}
    channels: dict[int, int] = {}
    topics: dict[str, int] = {}
    messages = 0
    for record in _records(source):
        if isinstance(record, Header) and not started:
            writer.start(profile=record.profile, library=record.library)
            started = True
        elif isinstance(record, Schema) and record.id not in schemas:
            schemas[record.id] = writer.register_schema(record.name, record.encoding, record.data)
        elif isinstance(record, Channel) and record.id not in channels:
            channels[record.id] = writer.register_channel(
                record.topic, record.message_encoding, schemas.get(record.schema_id, 0), record.metadata
            )
            topics[record.topic] = channels[record.id]
        elif isinstance(record, Message):
            if record.channel_id not in channels:
                raise _unknown_channel(source, record)
            writer.add_message(channels[record.channel_id], log_time=record.log_time, data=record.data,
                               publish_time=record.publish_time, sequence=record.sequence)
            messages += 1
    if not started:
        raise RecordingError(f"{source} is not a recording: it holds no MCAP header")
    return Copied(messages, topics)


FOOTER = struct.Struct("<BQQQI")  # opcode, record length (20), summary start, summary offset start, summary crc
MAGIC = b"\x89MCAP0\r\n"


def closed_cleanly(path: str | Path) -> bool:
    """Whether the recording ends as a clean close ends it: a Footer that points at a summary. A
    file cut by a crash, or ended by the server's provisional end (no summary), has not; the
    session it records was still open when the server stopped."""
    with open(path, "rb") as stream:
        stream.seek(0, 2)
        size = stream.tell()
        if size < FOOTER.size + len(MAGIC):
            return False
        stream.seek(size - FOOTER.size - len(MAGIC))
        tail = stream.read()
    opcode, length, summary_start, _, _ = FOOTER.unpack(tail[: FOOTER.size])
    return tail[FOOTER.size :] == MAGIC and opcode == 0x02 and length == 20 and summary_start > 0


def repair(source: str | Path, target: str | Path) -> int:
    """Write ``target`` with every message ``source`` holds and the summary and index a clean close
    appends, so any MCAP reader opens it (``target`` is removed if that fails); the message count."""
    try:
        with open(target, "wb") as stream:
            writer = Writer(stream, compression=CompressionType.ZSTD)
            copied = copy_records(source, writer)
            writer.finish()
    except BaseException:
        Path(target).unlink(missing_ok=True)
        raise
    return copied.messages


@dataclass
class Recording:
    """The ogapi messages of one recording, parsed."""

    config: pb.SessionConfig | None
    frames: list[tuple[int, pb.Frame]]  # (log time ns, frame)
    acks: list[pb.FrameAck]
    stats: pb.Stats | None
    # CorrectPoses batches, in the order they were applied (none in recordings written before they existed)
    corrections: list[pb.PoseCorrections] = field(default_factory=list)


def load(path: str | Path) -> Recording:
    """The recording's ogapi messages; ``RecordingError`` for a damaged file or message."""
    recording = Recording(config=None, frames=[], acks=[], stats=None)
    for item in read_messages(path, {TOPIC_SESSION, TOPIC_FRAMES, TOPIC_ACKS, TOPIC_STATS, TOPIC_CORRECTIONS}):
        try:
            if item.topic == TOPIC_SESSION:
                recording.config = pb.SessionConfig.FromString(item.data)
            elif item.topic == TOPIC_FRAMES:
                recording.frames.append((item.log_time_ns, pb.Frame.FromString(item.data)))
            elif item.topic == TOPIC_ACKS:
                recording.acks.append(pb.FrameAck.FromString(item.data))
            elif item.topic == TOPIC_CORRECTIONS:
                recording.corrections.append(pb.PoseCorrections.FromString(item.data))
            else:
                recording.stats = pb.Stats.FromString(item.data)
        except DecodeError:
            raise RecordingError(f"{path} is not a readable recording: a damaged {item.topic} message") from None
    return recording
