"""One MCAP file per session: the ogapi messages a replay needs, plus Foxglove channels to look at.

Every frame is followed by a flush that closes the MCAP chunk in progress, so a crash loses at
most the acks after the last frame; a clean close appends the summary and index.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from google.protobuf.timestamp_pb2 import Timestamp
from mcap.well_known import MessageEncoding
from mcap.writer import CompressionType, Writer
from mcap_protobuf.schema import register_schema
from ogapi import recording as layout
from ogapi.images import encode_color, encode_depth
from ogapi.v1 import mapping_pb2 as pb

from ogmapping.camera import Intrinsics
from ogmapping.frame import Frame

PROFILE = "protobuf"


def quaternion(rotation: np.ndarray) -> tuple[float, float, float, float]:
    """(x, y, z, w) of a rotation matrix, branching on the largest diagonal term for stability."""
    r = np.asarray(rotation, dtype=np.float64)
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        w, x, y, z = 0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        w, x, y, z = (r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        w, x, y, z = (r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s
    else:
        s = 2.0 * np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        w, x, y, z = (r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s
    norm = float(np.sqrt(w * w + x * x + y * y + z * z))
    return x / norm, y / norm, z / norm, w / norm


def _timestamp(nanoseconds: int) -> Timestamp:
    stamp = Timestamp()
    stamp.FromNanoseconds(nanoseconds)
    return stamp


def _calibration(camera: Intrinsics, stamp: Timestamp) -> CameraCalibration:
    fx, fy, cx, cy = camera.fx, camera.fy, camera.cx - 0.5, camera.cy - 0.5  # Foxglove: pixel centres at integers
    return CameraCalibration(
        timestamp=stamp, frame_id=layout.CAMERA_FRAME, width=camera.width, height=camera.height,
        distortion_model="plumb_bob", D=[0.0] * 5,
        K=[fx, 0, cx, 0, fy, cy, 0, 0, 1], R=[1, 0, 0, 0, 1, 0, 0, 0, 1], P=[fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0],
    )


class Recorder:
    """Thread-safe writer of one session's recording."""

    def __init__(self, path: Path, config: pb.SessionConfig) -> None:
        self.path = path
        path.parent.mkdir(parents=True, exist_ok=True)
        self._file = open(path, "wb")  # noqa: SIM115 - lives as long as the session
        self._writer = Writer(self._file, compression=CompressionType.ZSTD)
        self._writer.start(profile=PROFILE, library="ogserver")
        self._channels: dict[str, int] = {}
        self._lock = threading.Lock()
        self._closed = False
        with self._lock:
            self._write(layout.TOPIC_SESSION, config, time.time_ns())
            self._writer.flush()

    def _write(self, topic: str, message: Any, log_time: int, publish_time: int | None = None) -> None:
        channel = self._channels.get(topic)
        if channel is None:
            schema = register_schema(self._writer, type(message))
            channel = self._writer.register_channel(topic, MessageEncoding.Protobuf, schema)
            self._channels[topic] = channel
        self._writer.add_message(
            channel, log_time=log_time, data=message.SerializeToString(),
            publish_time=log_time if publish_time is None else publish_time,
        )

    def write_frame(self, message: pb.Frame, frame: Frame, received_ns: int) -> None:
        """The frame as received, then its Foxglove views, then a flush to disk."""
        sensor_ns = round(frame.timestamp * 1e9) if frame.timestamp is not None else received_ns
        stamp = _timestamp(sensor_ns)
        if message.color.encoding in (pb.COLOR_JPEG, pb.COLOR_PNG):
            color_data = message.color.data
            color_format = "jpeg" if message.color.encoding == pb.COLOR_JPEG else "png"
        else:
            color_data, color_format = encode_color(frame.rgb, pb.COLOR_PNG), "png"
        depth_data = (
            message.depth.data if message.depth.encoding == pb.DEPTH_PNG16
            else encode_depth(frame.depth, pb.DEPTH_PNG16, 1000.0)
        )
        x, y, z, w = quaternion(frame.c2w[:3, :3])
        tx, ty, tz = (float(v) for v in frame.c2w[:3, 3])
        views: list[tuple[str, Any]] = [
            (layout.TOPIC_FRAMES, message),
            (layout.TOPIC_COLOR, CompressedImage(
                timestamp=stamp, frame_id=layout.CAMERA_FRAME, data=color_data, format=color_format)),
            (layout.TOPIC_DEPTH, CompressedImage(
                timestamp=stamp, frame_id=layout.CAMERA_FRAME, data=depth_data, format="png")),
            (layout.TOPIC_CALIBRATION, _calibration(frame.color_intrinsics, stamp)),
            (layout.TOPIC_TRANSFORM, FrameTransform(
                timestamp=stamp, parent_frame_id=layout.WORLD_FRAME, child_frame_id=layout.CAMERA_FRAME,
                translation=Vector3(x=tx, y=ty, z=tz), rotation=Quaternion(x=x, y=y, z=z, w=w))),
        ]
        with self._lock:
            if self._closed:
                return
            for topic, view in views:
                self._write(topic, view, received_ns, sensor_ns)
            self._writer.flush()

    def write_ack(self, ack: pb.FrameAck) -> None:
        with self._lock:
            if not self._closed:
                self._write(layout.TOPIC_ACKS, ack, time.time_ns())

    def close(self, stats: pb.Stats | None = None) -> None:
        """Write the final stats and the summary; later writes are ignored."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
            if stats is not None:
                self._write(layout.TOPIC_STATS, stats, time.time_ns())
            self._writer.finish()
            self._file.close()
