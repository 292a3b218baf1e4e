"""One MCAP file per session: the ogapi messages a replay needs, plus Foxglove channels to look at
(the input frames, their refined poses when the session refines poses, and at keyframes the map's
render and points, written by the live view).

A frame is recorded when the session's worker takes it up, before it is mapped, and each frame is
followed by a flush that writes the MCAP chunk in progress and a provisional end (``RecordingFile``):
a crash loses at most the acks after the last frame, and leaves a file any MCAP reader opens; a clean
close appends the summary and index. The first write that fails (a full disk) stops the recording
for good: the file is cut back to the last complete frame, and closing rewrites it with a summary.
A session resumed after a crash goes on with its recording (``Recorder.resume``): the cut file is
copied into a new one, which replaces it, and later frames are appended there. With shared storage
at a URL (cluster mode, ``shared_store.py``) each flush's bytes are uploaded too, before the flush returns.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import grpc
import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.message import Message
from google.protobuf.timestamp_pb2 import Timestamp
from mcap.data_stream import RecordBuilder
from mcap.records import DataEnd, Footer
from mcap.well_known import MessageEncoding
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer
from mcap_protobuf.schema import register_schema
from ogapi import recording as layout
from ogapi.images import encode_color, encode_depth
from ogapi.v1 import mapping_pb2 as pb

from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.frame import Frame
from ogmapping.frames.rotation import matrix_to_quaternion
from ogserver.errors import ServiceError
from ogserver.recording.disk import StorageError, storage_error

log = logging.getLogger(__name__)
PROFILE = "protobuf"


class RecordingParts(Protocol):
    """Where else a recording's bytes go as they are committed (``shared_store.RecordingParts``: an fsspec store)."""

    def add(self, offset: int, data: bytes, end: bool) -> None: ...

    def publish(self, finished: Path) -> None: ...


def timestamp(nanoseconds: int) -> Timestamp:
    stamp = Timestamp()
    stamp.FromNanoseconds(nanoseconds)
    return stamp


def transform(sensor_ns: int, c2w: np.ndarray, parent: str, child: str) -> FrameTransform:
    """The camera's pose as Foxglove's transform from ``parent`` (the world) to ``child`` (the camera)."""
    x, y, z, w = matrix_to_quaternion(c2w[:3, :3])
    tx, ty, tz = (float(v) for v in c2w[:3, 3])
    return FrameTransform(timestamp=timestamp(sensor_ns), parent_frame_id=parent, child_frame_id=child,
                          translation=Vector3(x=tx, y=ty, z=tz), rotation=Quaternion(x=x, y=y, z=z, w=w))


def _calibration(camera: Intrinsics, stamp: Timestamp) -> CameraCalibration:
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx - 0.5, camera.cy - 0.5  # Foxglove: pixel centres at integers
    return CameraCalibration(
        timestamp=stamp, frame_id=layout.CAMERA_FRAME, width=camera.width, height=camera.height,
        distortion_model="plumb_bob", D=[0.0] * 5,
        K=[fx, 0, cx, 0, fy, cy, 0, 0, 1], R=[1, 0, 0, 0, 1, 0, 0, 0, 1], P=[fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0],
    )


def _provisional_end() -> bytes:
    """DataEnd, a Footer that announces no summary, and the closing magic: what makes a file an MCAP."""
    builder = RecordBuilder()
    DataEnd(data_section_crc=0).write(builder)
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(builder)
    return builder.end() + MCAP0_MAGIC


PROVISIONAL_END = _provisional_end()


class RecordingFile:
    """The file under the MCAP writer: bytes reach the disk only at a flush, which also writes
    ``PROVISIONAL_END`` after them for the next flush to overwrite, so a file cut between two
    flushes is a complete MCAP. A flush that fails is cut back to the one before; so is one whose bytes
    could not be uploaded to the shared storage's ``parts``."""

    def __init__(self, path: Path, parts: RecordingParts | None = None) -> None:
        self._file = open(path, "wb", buffering=0)  # noqa: SIM115 - lives as long as the recording
        self._parts = parts
        self._pending = bytearray()
        self._committed = 0  # bytes of MCAP data on disk; what follows them is ``_end``
        self._end = b""

    def write(self, data: bytes) -> int:
        self._pending += data
        return len(data)

    def tell(self) -> int:
        return self._committed + len(self._pending)

    def flush(self) -> None:
        self._commit(PROVISIONAL_END)

    def finish(self) -> None:
        """Write what the MCAP writer's ``finish`` left: the real end (never shorter than the provisional one)."""
        self._commit(b"")

    def close(self) -> None:
        self._file.close()

    def sync(self) -> None:
        """To the disk, not only to the OS (a flush survives the process, this a power cut too)."""
        os.fsync(self._file.fileno())

    def _commit(self, end: bytes) -> None:
        data = bytes(self._pending) + end
        self._pending.clear()
        try:
            self._write_at(self._committed, data)
            if self._parts is not None:
                self._parts.add(self._committed, data[: len(data) - len(end)], end=not end)
        except OSError:
            with contextlib.suppress(OSError):  # in place, so a full disk takes it; readers stop at a cut anyway
                self._file.truncate(self._committed + len(self._end))
                self._write_at(self._committed, self._end)
            raise
        self._committed += len(data) - len(end)
        self._end = end

    def _write_at(self, offset: int, data: bytes) -> None:
        self._file.seek(offset)
        view = memoryview(data)
        while view:
            view = view[self._file.write(view):]


class _Channels:
    """An MCAP writer with one protobuf channel per topic, registered on first use."""

    def __init__(self, writer: Writer, channels: dict[str, int] | None = None) -> None:
        self.writer = writer
        self._channels = dict(channels or {})

    def add(self, topic: str, message: Message, log_time: int, publish_time: int | None = None) -> None:
        channel = self._channels.get(topic)
        if channel is None:
            schema = register_schema(self.writer, type(message))
            channel = self.writer.register_channel(topic, MessageEncoding.Protobuf, schema)
            self._channels[topic] = channel
        self.writer.add_message(
            channel, log_time=log_time, data=message.SerializeToString(),
            publish_time=log_time if publish_time is None else publish_time,
        )


@dataclass(frozen=True)
class FrameRecord:
    """One frame as the recording holds it: the message as received, then its Foxglove views."""

    received_ns: int
    sensor_ns: int
    views: list[tuple[str, Message]]

    @property
    def size(self) -> int:
        """Its messages' bytes before compression: what it costs the recording, at most."""
        return sum(view.ByteSize() for _, view in self.views)


def frame_record(message: pb.Frame, frame: Frame, received_ns: int) -> FrameRecord:
    """Encoded off the worker's path (raw images become PNGs for Foxglove); validation bounds the timestamp."""
    sensor_ns = round(frame.timestamp * 1e9) if frame.timestamp is not None else received_ns
    stamp = timestamp(sensor_ns)
    if message.color.encoding in (pb.COLOR_JPEG, pb.COLOR_PNG):
        color_data = message.color.data
        color_format = "jpeg" if message.color.encoding == pb.COLOR_JPEG else "png"
    else:
        color_data, color_format = encode_color(frame.rgb, pb.COLOR_PNG), "png"
    depth_data = (
        message.depth.data if message.depth.encoding == pb.DEPTH_PNG16
        else encode_depth(frame.depth, pb.DEPTH_PNG16, 1000.0)
    )
    return FrameRecord(received_ns, sensor_ns, [
        (layout.TOPIC_FRAMES, message),
        (layout.TOPIC_COLOR, CompressedImage(
            timestamp=stamp, frame_id=layout.CAMERA_FRAME, data=color_data, format=color_format)),
        (layout.TOPIC_DEPTH, CompressedImage(
            timestamp=stamp, frame_id=layout.CAMERA_FRAME, data=depth_data, format="png")),
        (layout.TOPIC_CALIBRATION, _calibration(frame.color_intrinsics, stamp)),
        (layout.TOPIC_TRANSFORM, transform(sensor_ns, frame.c2w, layout.WORLD_FRAME, layout.CAMERA_FRAME)),
    ])


def _open_mcap(path: Path, parts: RecordingParts | None = None) -> tuple[RecordingFile, Writer]:
    file = RecordingFile(path, parts)
    return file, Writer(file, compression=CompressionType.ZSTD)


class Recorder:
    """Thread-safe writer of one session's recording. Every write failure is a ``StorageError``;
    after the first, ``failure`` holds it and frames are refused with it. With ``parts`` (shared storage),
    every flush is uploaded as well and the closed recording is published there."""

    def __init__(self, path: Path, config: pb.SessionConfig, parts: RecordingParts | None = None) -> None:
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            file, writer = _open_mcap(path, parts)
        except OSError as error:
            log.error("recording %s: cannot create it: %s", path, error)
            raise storage_error(error, "a new session's recording") from None
        self._attach(path, file, _Channels(writer), parts)
        try:
            writer.start(profile=PROFILE, library="ogserver")
            self._mcap.add(layout.TOPIC_SESSION, config, time.time_ns())
            writer.flush()
        except OSError as error:
            self._file.close()
            path.unlink(missing_ok=True)  # no empty file for a session that never opened
            log.error("recording %s: cannot start it: %s", path, error)
            raise storage_error(error, "a new session's recording") from None

    def _attach(self, path: Path, file: RecordingFile, mcap: _Channels, parts: RecordingParts | None) -> None:
        self.path = path
        self._parts = parts
        self.failure: StorageError | None = None
        self._lock = threading.Lock()
        self._closed = False
        self._file = file
        self._mcap = mcap

    @classmethod
    def resume(cls, path: Path, parts: RecordingParts | None = None) -> Recorder:
        """Go on with a recording a crash cut: what it holds (``layout.read_messages`` reads up to the
        cut) is copied into a new file, ended and synced, which then replaces it, so the session keeps
        one recording and a crash during this leaves the old file as it was. Needs as much free space
        as the recording takes. StorageError if it cannot be written, RecordingError if it cannot be read.
        With ``parts``, the copy is uploaded whole as a new generation of parts."""
        partial = path.with_name(path.name + ".resumed")
        try:
            file, writer = _open_mcap(partial, parts)
            try:
                copied = layout.copy_records(path, writer)
                writer.flush()
                file.sync()
            except BaseException:
                file.close()
                raise
            os.replace(partial, path)
        except OSError as error:
            partial.unlink(missing_ok=True)
            log.error("recording %s: cannot go on with it: %s", path, error)
            raise storage_error(error, "the resumed session's recording") from None
        except BaseException:
            partial.unlink(missing_ok=True)
            raise
        recorder = cls.__new__(cls)
        recorder._attach(path, file, _Channels(writer, copied.channels), parts)
        return recorder

    def _fail(self, error: Exception) -> StorageError:
        """Stop recording for good: the file holds every frame up to the last one written whole."""
        if isinstance(error, OSError):
            log.error("recording %s failed: %s", self.path, error)
            failure = storage_error(error, "the session's recording")
        else:
            log.exception("recording %s failed", self.path)
            failure = StorageError(grpc.StatusCode.INTERNAL,
                                   f"the server could not write the session's recording: {type(error).__name__}")
        self.failure = StorageError(failure.code, f"{failure.message}; the session takes no more frames")
        return self.failure

    def _check_open(self) -> None:
        if self._closed:
            raise ServiceError(grpc.StatusCode.ABORTED, "the session was closed")
        if self.failure is not None:
            raise self.failure

    def write_frame(self, record: FrameRecord) -> None:
        """The frame and its views, then a flush to disk: once this returns, a crash keeps the frame."""
        with self._lock:
            self._check_open()
            try:
                for topic, view in record.views:
                    self._mcap.add(topic, view, record.received_ns, record.sensor_ns)
                self._mcap.writer.flush()
            except Exception as error:
                raise self._fail(error) from None

    def write_ack(self, ack: pb.FrameAck, sensor_ns: int | None = None) -> None:
        """Buffered with the next frame's flush; after a close (a frame outlasting it), dropped. An ack
        with a pose correction comes with the frame's refined pose (at ``sensor_ns``) for Foxglove."""
        items: list[tuple[str, Message]] = [(layout.TOPIC_ACKS, ack)]
        if ack.HasField("pose_correction") and sensor_ns is not None:
            refined = np.array(ack.pose_correction.refined_c2w, dtype=np.float64).reshape(4, 4)
            items.append((layout.TOPIC_REFINED_TRANSFORM,
                          transform(sensor_ns, refined, layout.WORLD_FRAME, layout.REFINED_CAMERA_FRAME)))
        self._write_late(items, flush=False)

    def write_corrections(self, corrections: pb.PoseCorrections) -> None:
        """A batch of pose corrections the map took, flushed at once: a resume applies it again."""
        self._write_late([(layout.TOPIC_CORRECTIONS, corrections)], flush=True)

    def write_views(self, views: list[tuple[str, Message]], sensor_ns: int) -> None:
        """The map as of a keyframe (its render, its points), flushed at once: the thread that made
        them compresses them, not the session's worker at its next frame. After a close, dropped."""
        self._write_late(views, flush=True, publish_time=sensor_ns)

    def _write_late(self, items: list[tuple[str, Message]], flush: bool, publish_time: int | None = None) -> None:
        """Messages about frames already recorded, logged now."""
        with self._lock:
            if self._closed:
                return
            self._check_open()
            try:
                now = time.time_ns()
                for topic, message in items:
                    self._mcap.add(topic, message, now, publish_time)
                if flush:
                    self._mcap.writer.flush()
            except Exception as error:
                raise self._fail(error) from None

    def close(self, stats: pb.Stats | None = None) -> None:
        """Write the final stats and the summary; later writes are dropped. A recording that failed
        is rewritten with a summary instead; if that fails too (StorageError), closing can be retried, as
        it can when the finished recording cannot be published to the shared storage."""
        with self._lock:
            if not self._closed:
                self._finish(stats)
            if self._parts is not None:
                try:
                    self._parts.publish(self.path)
                except OSError as error:
                    log.error("recording %s: cannot publish it to the shared storage: %s", self.path, error)
                    raise storage_error(error, "the session's recording to the shared storage") from None

    def _finish(self, stats: pb.Stats | None) -> None:
        if self.failure is None:
            try:
                if stats is not None:
                    self._mcap.add(layout.TOPIC_STATS, stats, time.time_ns())
                self._mcap.writer.finish()
                self._file.finish()
            except Exception as error:
                self._fail(error)
        if self.failure is not None:
            self._rewrite(stats)
        self._file.close()
        self._closed = True

    def _rewrite(self, stats: pb.Stats | None) -> None:
        """A failed recording, finished: what its file holds, copied into a new one with the stats and
        a summary (this needs as much free space as the recording takes), which then replaces it."""
        partial = self.path.with_name(self.path.name + ".partial")
        try:
            file, writer = _open_mcap(partial)
            try:
                copied = layout.copy_records(self.path, writer)
                if stats is not None:
                    _Channels(writer, copied.channels).add(layout.TOPIC_STATS, stats, time.time_ns())
                writer.finish()
                file.finish()
            finally:
                file.close()
            os.replace(partial, self.path)
        except OSError as error:
            partial.unlink(missing_ok=True)
            log.error("recording %s: cannot finish it: %s", self.path, error)
            raise storage_error(error, "the session's recording") from None
