"""An open bag through ``rosbags.highlevel.AnyReader``: its topics, messages in order, one message again.

ROS 1 bags and ROS 2 bags (a folder with metadata.yaml, or one .mcap / .db3 file) open the same
way. ROS 2 bags recorded before Humble carry no message definitions; the Humble type store stands
in for them. A message is found again by its topic, its receive time in the bag and its rank among
the messages of that topic at that time: every storage seeks by time, so loading frame N reads
one chunk, not the bag up to N. ``rosbags`` readers are not thread-safe; a lock serialises them
(frames are prefetched on a thread).
"""

from __future__ import annotations

import struct
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from rosbags.highlevel import AnyReader, AnyReaderError
from rosbags.typesys import Stores, get_typestore

from ogmapping.datasets.rosbag.layout import ROS1_SUFFIX, check_signature


@dataclass(frozen=True)
class TopicEntry:
    name: str
    msgtype: str
    count: int


@dataclass(frozen=True)
class MessageRef:
    """Where to find one message again."""

    topic: str
    bag_time_ns: int
    rank: int  # among this topic's messages with the same bag time


class BagFile:
    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise ValueError(f"bag does not exist: {self.path}")
        self.ros2 = not (self.path.is_file() and self.path.suffix == ROS1_SUFFIX)
        check_signature(self.path)
        try:
            self._reader = AnyReader([self.path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            self._reader.open()
        except (AnyReaderError, ValueError, TypeError, struct.error) as error:  # what rosbags raises on damage
            first_line = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
            raise ValueError(f"cannot open {self.path} as a ROS bag: {first_line}") from error
        self._lock = threading.Lock()
        self.topics = {
            name: TopicEntry(name, info.msgtype or "(several types)", info.msgcount)
            for name, info in sorted(self._reader.topics.items())
        }

    def close(self) -> None:
        with self._lock:
            self._reader.close()

    def _connections(self, topic: str) -> list:
        return [c for c in self._reader.connections if c.topic == topic]

    def deserialize(self, raw: bytes | memoryview, msgtype: str, topic: str) -> object:
        try:
            return self._reader.deserialize(raw, msgtype)
        except AnyReaderError as error:
            raise ValueError(f"{self.path}: cannot decode a message on {topic}: {error}") from error

    def first(self, topic: str) -> object | None:
        """The first message on ``topic``, decoded, or None if it has none."""
        connections = self._connections(topic)
        if not connections:
            return None
        with self._lock:
            for connection, _, raw in self._reader.messages(connections=connections):
                return self.deserialize(raw, connection.msgtype, topic)
        return None

    def scan(self, topics: list[str]) -> Iterator[tuple[MessageRef, str, bytes]]:
        """Every message on ``topics`` in bag-time order: the reference that finds it again, its type, its bytes.

        Holds the lock throughout: finish (or close) the iterator before loading frames.
        """
        connections = [c for topic in topics for c in self._connections(topic)]
        if not connections:  # rosbags reads every topic when given none
            return
        ranks: dict[tuple[str, int], int] = {}
        with self._lock:
            for connection, bag_time, raw in self._reader.messages(connections=connections):
                key = (connection.topic, bag_time)
                ranks[key] = ranks.get(key, -1) + 1
                yield MessageRef(connection.topic, bag_time, ranks[key]), connection.msgtype, raw

    def load(self, ref: MessageRef) -> object:
        """The message ``ref`` points at, decoded."""
        with self._lock:
            messages = self._reader.messages(connections=self._connections(ref.topic), start=ref.bag_time_ns,
                                             stop=ref.bag_time_ns + 1)
            for rank, (connection, _, raw) in enumerate(messages):
                if rank == ref.rank:
                    return self.deserialize(raw, connection.msgtype, ref.topic)
        raise ValueError(f"{self.path}: message {ref.rank} at bag time {ref.bag_time_ns} ns on {ref.topic} is gone")
