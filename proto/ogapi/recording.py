"""The layout of a session recording (MCAP, protobuf) and a reader that survives a crashed writer.

The server flushes a complete MCAP chunk after every frame, so a file cut off by a crash holds
every frame up to the last one written; ``read_messages`` streams through it without needing the
summary section a clean close appends.
"""

from __future__ import annotations

import struct
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from mcap.exceptions import EndOfFile
from mcap.reader import NonSeekingReader

from ogapi.v1 import mapping_pb2 as pb

TOPIC_SESSION = "/ogmap/session"  # ogapi.v1.SessionConfig, first message
TOPIC_FRAMES = "/ogmap/frames"  # ogapi.v1.Frame, every accepted frame as received
TOPIC_ACKS = "/ogmap/acks"  # ogapi.v1.FrameAck, one per mapped frame
TOPIC_STATS = "/ogmap/stats"  # ogapi.v1.Stats, at close
TOPIC_COLOR = "/camera/color"  # foxglove.CompressedImage
TOPIC_DEPTH = "/camera/depth"  # foxglove.CompressedImage, 16-bit PNG
TOPIC_CALIBRATION = "/camera/calibration"  # foxglove.CameraCalibration
TOPIC_TRANSFORM = "/tf"  # foxglove.FrameTransform, world -> camera
WORLD_FRAME = "world"
CAMERA_FRAME = "camera"


@dataclass(frozen=True)
class RecordedMessage:
    topic: str
    schema: str
    log_time_ns: int
    data: bytes


def read_messages(path: str | Path, topics: set[str] | None = None) -> Iterator[RecordedMessage]:
    """Messages in file order; a file that ends mid-record (a crashed writer) just ends early."""
    with open(path, "rb") as stream:
        reader = NonSeekingReader(stream)
        messages = reader.iter_messages(topics=topics, log_time_order=False)
        while True:
            try:
                schema, channel, message = next(messages)
            except StopIteration:
                return
            except (EndOfFile, struct.error):  # the file ends inside a record
                return
            yield RecordedMessage(channel.topic, schema.name if schema else "", message.log_time, message.data)


@dataclass
class Recording:
    """The ogapi messages of one recording, parsed."""

    config: pb.SessionConfig | None
    frames: list[tuple[int, pb.Frame]]  # (log time ns, frame)
    acks: list[pb.FrameAck]
    stats: pb.Stats | None


def load(path: str | Path) -> Recording:
    recording = Recording(config=None, frames=[], acks=[], stats=None)
    for item in read_messages(path, {TOPIC_SESSION, TOPIC_FRAMES, TOPIC_ACKS, TOPIC_STATS}):
        if item.topic == TOPIC_SESSION:
            recording.config = pb.SessionConfig.FromString(item.data)
        elif item.topic == TOPIC_FRAMES:
            recording.frames.append((item.log_time_ns, pb.Frame.FromString(item.data)))
        elif item.topic == TOPIC_ACKS:
            recording.acks.append(pb.FrameAck.FromString(item.data))
        else:
            recording.stats = pb.Stats.FromString(item.data)
    return recording
