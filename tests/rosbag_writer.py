"""Writes ROS 1 and ROS 2 test bags with ``rosbags``, as a robot's recorder would, from known frames.

Messages are built from the distro's own type store (Noetic for ROS 1, Humble for ROS 2), so the
bytes are what ``rosbag record`` / ``ros2 bag record`` would write; compressedDepth payloads follow
compressed_depth_image_transport's layout (12-byte ConfigHeader, then a PNG).
"""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

from ogmapping.frames.rotation import matrix_to_quaternion


class BagRecorder:
    """One bag being written: ``add`` a topic, then ``write`` messages built by the helpers below."""

    def __init__(self, path: Path, ros2: bool, storage: str = "mcap") -> None:
        self.ros2 = ros2
        self.store = get_typestore(Stores.ROS2_HUMBLE if ros2 else Stores.ROS1_NOETIC)
        if not ros2:  # Noetic's store lacks tf2_msgs; its definition is the one tf2_msgs ships
            self.store.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms",
                                                   "tf2_msgs/msg/TFMessage"))
        if ros2:
            plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
            self.writer = Writer2(path, version=9, storage_plugin=plugin)
        else:
            self.writer = Writer1(path)
        self.connections: dict[str, object] = {}
        self.types: dict[str, str] = {}

    def __enter__(self) -> BagRecorder:
        self.writer.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.writer.close()

    def t(self, name: str) -> type:
        return self.store.types[name]

    def write(self, topic: str, stamp_ns: int, message: object) -> None:
        msgtype = message.__msgtype__  # type: ignore[attr-defined]
        if topic not in self.connections:
            self.connections[topic] = self.writer.add_connection(topic, msgtype, typestore=self.store)
        data = (self.store.serialize_cdr(message, msgtype) if self.ros2
                else self.store.serialize_ros1(message, msgtype))
        self.writer.write(self.connections[topic], stamp_ns, data)  # type: ignore[arg-type]

    # Message builders.

    def header(self, stamp_ns: int, frame: str) -> object:
        stamp = self.t("builtin_interfaces/msg/Time")(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
        if self.ros2:
            return self.t("std_msgs/msg/Header")(stamp=stamp, frame_id=frame)
        return self.t("std_msgs/msg/Header")(seq=0, stamp=stamp, frame_id=frame)

    def image(self, stamp_ns: int, frame: str, pixels: np.ndarray, encoding: str, big_endian: bool = False,
              pad: int = 0) -> object:
        """A raw Image of ``pixels`` (H, W[, C]) in their dtype, rows padded by ``pad`` bytes."""
        array = np.ascontiguousarray(pixels)
        if big_endian:
            array = array.astype(array.dtype.newbyteorder(">"))
        height, width = array.shape[:2]
        rows = array.reshape(height, -1).view(np.uint8)
        if pad:
            rows = np.concatenate([rows, np.full((height, pad), 7, np.uint8)], axis=1)
        return self.t("sensor_msgs/msg/Image")(
            header=self.header(stamp_ns, frame), height=height, width=width, encoding=encoding,
            is_bigendian=int(big_endian), step=rows.shape[1], data=np.ascontiguousarray(rows).ravel())

    def compressed(self, stamp_ns: int, frame: str, data: bytes, format: str) -> object:
        return self.t("sensor_msgs/msg/CompressedImage")(
            header=self.header(stamp_ns, frame), format=format, data=np.frombuffer(data, np.uint8).copy())

    def camera_info(self, stamp_ns: int, frame: str, width: int, height: int, k: tuple[float, float, float, float],
                    model: str = "plumb_bob", distortion: tuple[float, ...] = (0.0,) * 5) -> object:
        fx, fy, cx, cy = k
        matrix = np.array([fx, 0, cx, 0, fy, cy, 0, 0, 1], dtype=np.float64)
        projection = np.array([fx, 0, cx, 0, 0, fy, cy, 0, 0, 0, 1, 0], dtype=np.float64)
        names = ("d", "k", "r", "p") if self.ros2 else ("D", "K", "R", "P")
        fields = dict(zip(names, (np.array(distortion, np.float64), matrix, np.eye(3).ravel(), projection),
                          strict=True))
        roi = self.t("sensor_msgs/msg/RegionOfInterest")(x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return self.t("sensor_msgs/msg/CameraInfo")(
            header=self.header(stamp_ns, frame), height=height, width=width, distortion_model=model,
            binning_x=0, binning_y=0, roi=roi, **fields)

    def _pose(self, pose: np.ndarray) -> object:
        x, y, z, w = matrix_to_quaternion(pose[:3, :3])
        return self.t("geometry_msgs/msg/Pose")(
            position=self.t("geometry_msgs/msg/Point")(x=float(pose[0, 3]), y=float(pose[1, 3]), z=float(pose[2, 3])),
            orientation=self.t("geometry_msgs/msg/Quaternion")(x=x, y=y, z=z, w=w))

    def tf(self, stamp_ns: int, edges: list[tuple[str, str, np.ndarray]]) -> object:
        """A TFMessage of (parent, child, pose of child in parent) edges."""
        transforms = []
        for parent, child, pose in edges:
            p = self._pose(pose)
            transform = self.t("geometry_msgs/msg/Transform")(
                translation=self.t("geometry_msgs/msg/Vector3")(x=p.position.x, y=p.position.y, z=p.position.z),
                rotation=p.orientation)
            transforms.append(self.t("geometry_msgs/msg/TransformStamped")(
                header=self.header(stamp_ns, parent), child_frame_id=child, transform=transform))
        return self.t("tf2_msgs/msg/TFMessage")(transforms=transforms)

    def pose_stamped(self, stamp_ns: int, frame: str, pose: np.ndarray) -> object:
        return self.t("geometry_msgs/msg/PoseStamped")(header=self.header(stamp_ns, frame), pose=self._pose(pose))

    def path(self, stamp_ns: int, frame: str, poses: list[tuple[int, np.ndarray]]) -> object:
        """A nav_msgs/Path in ``frame`` of (stamp, pose) pairs, each a PoseStamped in that frame too."""
        return self.t("nav_msgs/msg/Path")(header=self.header(stamp_ns, frame),
                                           poses=[self.pose_stamped(t, frame, pose) for t, pose in poses])

    def odometry(self, stamp_ns: int, frame: str, child: str, pose: np.ndarray) -> object:
        covariance = np.zeros(36)
        zero = self.t("geometry_msgs/msg/Vector3")(x=0.0, y=0.0, z=0.0)
        return self.t("nav_msgs/msg/Odometry")(
            header=self.header(stamp_ns, frame), child_frame_id=child,
            pose=self.t("geometry_msgs/msg/PoseWithCovariance")(pose=self._pose(pose), covariance=covariance),
            twist=self.t("geometry_msgs/msg/TwistWithCovariance")(
                twist=self.t("geometry_msgs/msg/Twist")(linear=zero, angular=zero), covariance=covariance))


def encode_png(image: np.ndarray) -> bytes:
    ok, data = cv2.imencode(".png", image)
    assert ok
    return data.tobytes()


def compressed_depth_16(depth_mm: np.ndarray) -> bytes:
    """compressedDepth of a 16UC1 image: the header (format 0 = PNG, unused quantisation) and a 16-bit PNG."""
    return struct.pack("<iff", 0, 0.0, 0.0) + encode_png(depth_mm.astype(np.uint16))


def compressed_depth_32(depth_m: np.ndarray, quantization: float = 100.0, max_depth: float = 10.0) -> bytes:
    """compressedDepth of a 32FC1 image, quantised as compressed_depth_image_transport does."""
    quant_a = quantization * (quantization + 1.0)
    quant_b = 1.0 - quant_a / max_depth
    inverse = np.zeros(depth_m.shape, np.uint16)
    valid = np.isfinite(depth_m) & (depth_m > 0) & (depth_m < max_depth)
    inverse[valid] = np.round(quant_a / depth_m[valid] + quant_b).astype(np.uint16)
    return struct.pack("<iff", 0, quant_a, quant_b) + encode_png(inverse)
