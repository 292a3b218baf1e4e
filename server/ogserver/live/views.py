"""What a session's map looks like: the latest mapped frame, its render, the camera paths and the map as points.

The session's worker only hands over references (``LatestFrame.offer``: the frame's pose, its
recorded colour image); rendering and decoding the map happen later, on the live view's thread
(``publisher.py``), between the mapper's optimisation iterations like any render call (``map_look.py``).
The messages are Foxglove's schemas, the same bytes for the Foxglove WebSocket server and the session
recording.
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.PackedElementField_pb2 import PackedElementField
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.Pose_pb2 import Pose
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
from foxglove_schemas_protobuf.Quaternion_pb2 import Quaternion
from foxglove_schemas_protobuf.Vector3_pb2 import Vector3
from ogapi import recording as layout

from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.frame import Frame
from ogmapping.frames.rotation import matrix_to_quaternion
from ogmapping.optim.poses import PoseReport
from ogmapping.persist.export import ColoredPoints
from ogserver.recording.recorder import FrameRecord, timestamp

MAX_POSES = 1000  # poses kept between two looks of a reader; older ones are dropped
MAX_TRAJECTORY_POSES = 5000  # the newest poses a live trajectory shows
# Live only (foxglove.PosesInFrame): the session's camera path so far, as the client sent it and as refined.
TOPIC_TRAJECTORY = "/ogmap/trajectory"
TOPIC_REFINED_TRAJECTORY = "/ogmap/trajectory_refined"
POINT_STRIDE = 16  # x, y, z float32, then red, green, blue, alpha uint8
POINT_FIELDS = [
    *(PackedElementField(name=name, offset=4 * axis, type=PackedElementField.FLOAT32)
      for axis, name in enumerate(("x", "y", "z"))),
    *(PackedElementField(name=name, offset=12 + channel, type=PackedElementField.UINT8)
      for channel, name in enumerate(("red", "green", "blue", "alpha"))),
]


@dataclass(frozen=True)
class FrameIds:
    """Foxglove frame ids: ``world``/``camera`` in a recording (one session), prefixed live."""

    world: str = layout.WORLD_FRAME
    camera: str = layout.CAMERA_FRAME
    refined_camera: str = layout.REFINED_CAMERA_FRAME

    @classmethod
    def of_session(cls, session_id: str) -> FrameIds:
        return cls(f"{session_id}/{layout.WORLD_FRAME}", f"{session_id}/{layout.CAMERA_FRAME}",
                   f"{session_id}/{layout.REFINED_CAMERA_FRAME}")


@dataclass(frozen=True)
class MappedFrame:
    sensor_ns: int
    c2w: np.ndarray  # (4, 4)
    intrinsics: Intrinsics
    color: CompressedImage  # the input image as recorded
    keyframe: bool
    refined: np.ndarray | None = None  # (4, 4) the pose refinement left (``poses.refine``), else None

    @property
    def pose(self) -> np.ndarray:
        """The pose its map views are rendered from: the refined one, where the session refines poses."""
        return self.c2w if self.refined is None else self.refined

    @classmethod
    def of(cls, frame: Frame, record: FrameRecord, keyframe: bool, pose: PoseReport | None = None) -> MappedFrame:
        """``pose``: the frame's refined pose, in a session that refines poses."""
        color = next(view for topic, view in record.views if topic == layout.TOPIC_COLOR)
        return cls(record.sensor_ns, np.array(frame.c2w, dtype=np.float64), frame.color_intrinsics, color, keyframe,
                   None if pose is None else pose.refined_c2w)


@dataclass(frozen=True)
class Pending:
    """What a session mapped since the live view last looked."""

    latest: MappedFrame
    poses: list[tuple[int, np.ndarray]]  # (sensor ns, c2w) of every frame mapped since, oldest first
    keyframe: MappedFrame | None  # the newest keyframe among them
    refined: list[tuple[int, np.ndarray]] = field(default_factory=list)  # (sensor ns, refined c2w), likewise


@dataclass(frozen=True)
class Shown:
    """What the web view shows beside a session's map: the keyframe the recording's views rendered last, with
    that render, else the newest keyframe (views not recorded; the web view renders it); and the keyframes
    mapped so far, the map's version."""

    frame: MappedFrame | None
    render: bytes | None
    keyframes: int


class Latest(Protocol):
    """What the views read of the frames a session mapped: its ``LatestFrame``, or one in a worker process
    through calls."""

    def take(self) -> Pending | None: ...

    def shown(self) -> Shown: ...


class LatestFrame:
    """A mailbox from the session's worker to its readers: offering costs a lock and an append. Each reader
    (``take(reader)``: the live view's thread; and the server's, for a session in a worker process) gets what
    was mapped since it last took, the newest ``MAX_POSES`` poses of it."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._offered = 0  # frames offered so far: each reader's place counts them
        self._taken: dict[str, int] = {}  # reader -> frames offered when it last took
        self._latest: MappedFrame | None = None
        # (number, sensor ns, c2w, refined c2w or None) of the newest frames: their poses, not their images
        self._poses: deque[tuple[int, int, np.ndarray, np.ndarray | None]] = deque(maxlen=MAX_POSES)
        self._keyframe_number = 0  # the number of the newest keyframe
        self._keyframe: MappedFrame | None = None  # the newest keyframe mapped
        self._keyframes = 0  # keyframes offered so far: the web view's map version
        self.rendered: tuple[MappedFrame, bytes] | None = None  # the keyframe the live view last recorded, its JPEG

    def offer(self, frame: MappedFrame) -> None:
        with self._lock:
            self._offered += 1
            self._latest = frame
            self._poses.append((self._offered, frame.sensor_ns, frame.c2w, frame.refined))
            if frame.keyframe:
                self._keyframe = frame
                self._keyframes += 1
                self._keyframe_number = self._offered

    def take(self, reader: str = "") -> Pending | None:
        with self._lock:
            seen = self._taken.get(reader, 0)
            if self._offered == seen or self._latest is None:
                return None
            self._taken[reader] = self._offered
            poses = [(sensor_ns, c2w, refined) for number, sensor_ns, c2w, refined in self._poses if number > seen]
            keyframe = self._keyframe if self._keyframe_number > seen else None
            return Pending(self._latest, [(sensor_ns, c2w) for sensor_ns, c2w, _ in poses], keyframe,
                           [(sensor_ns, refined) for sensor_ns, _, refined in poses if refined is not None])

    def shown(self) -> Shown:
        with self._lock:
            rendered = self.rendered
            if rendered is not None:
                return Shown(rendered[0], rendered[1], self._keyframes)
            return Shown(self._keyframe, None, self._keyframes)


class Trajectory:
    """A session's camera path as the live view draws it: its newest ``MAX_TRAJECTORY_POSES`` poses."""

    def __init__(self) -> None:
        self.poses: deque[Pose] = deque(maxlen=MAX_TRAJECTORY_POSES)
        self.sensor_ns = 0

    def extend(self, poses: list[tuple[int, np.ndarray]]) -> None:
        for sensor_ns, c2w in poses:
            x, y, z, w = matrix_to_quaternion(c2w[:3, :3])
            tx, ty, tz = (float(v) for v in c2w[:3, 3])
            self.poses.append(Pose(position=Vector3(x=tx, y=ty, z=tz), orientation=Quaternion(x=x, y=y, z=z, w=w)))
            self.sensor_ns = sensor_ns

    def message(self, frames: FrameIds) -> PosesInFrame:
        return PosesInFrame(timestamp=timestamp(self.sensor_ns), frame_id=frames.world, poses=list(self.poses))


def image(jpeg: bytes, sensor_ns: int, frames: FrameIds) -> CompressedImage:
    return CompressedImage(timestamp=timestamp(sensor_ns), frame_id=frames.camera, data=jpeg, format="jpeg")


def points_message(points: ColoredPoints, sensor_ns: int, frames: FrameIds) -> PointCloud:
    packed = np.zeros(len(points.positions), dtype=[("xyz", "<f4", 3), ("rgba", "u1", 4)])
    packed["xyz"], packed["rgba"] = points.positions, points.rgba
    return PointCloud(timestamp=timestamp(sensor_ns), frame_id=frames.world, point_stride=POINT_STRIDE,
                      fields=POINT_FIELDS, data=packed.tobytes())
