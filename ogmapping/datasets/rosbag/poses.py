"""Where a camera was at an image stamp: from TF, or from a PoseStamped / Odometry topic.

TF: the chain of ``/tf`` and ``/tf_static`` transforms from a fixed frame (``--fixed-frame``,
default the root of the camera frame's tree, e.g. ``map`` or ``odom``) down to the camera's
optical frame, each edge interpolated at the image stamp. TF counts as a pose source only when an
edge on that chain moves; a tree of static transforms only mounts the camera.

A pose topic gives the pose of a body frame in the message's ``header.frame_id``: Odometry's
``child_frame_id``, or ``--body-frame``, and for PoseStamped without it the camera's optical frame
itself. When the body is not the camera, TF supplies the body-to-camera mounting.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ogmapping.datasets.rosbag.bagfile import BagFile
from ogmapping.datasets.rosbag.headers import normalise_frame, stamp_ns
from ogmapping.datasets.rosbag.options import BagOptions
from ogmapping.datasets.rosbag.topics import POSE_TYPES, TF_TYPES, of_types, topic_error
from ogmapping.datasets.rosbag.transforms import Track, TransformTree


def _vector(value: object) -> tuple[float, float, float]:
    return float(value.x), float(value.y), float(value.z)  # type: ignore[attr-defined]


def _quaternion(value: object) -> tuple[float, float, float, float]:
    return float(value.x), float(value.y), float(value.z), float(value.w)  # type: ignore[attr-defined]


def read_tf(bag: BagFile) -> TransformTree:
    """Every transform on the bag's TF topics (``*tf_static`` topics are static)."""
    tree = TransformTree()
    for ref, msgtype, raw in bag.scan(of_types(bag, TF_TYPES)):
        message = bag.deserialize(raw, msgtype, ref.topic)
        for item in message.transforms:  # type: ignore[attr-defined]
            tree.add(normalise_frame(item.header.frame_id), normalise_frame(item.child_frame_id),
                     stamp_ns(item.header.stamp), _vector(item.transform.translation),
                     _quaternion(item.transform.rotation), static=ref.topic.rstrip("/").endswith("tf_static"))
    return tree


@dataclass(frozen=True)
class StampedPose:
    """One pose message: the pose of ``child`` (Odometry's child frame, else '') in ``frame`` at ``stamp_ns``."""

    frame: str
    child: str
    stamp_ns: int
    translation: tuple[float, float, float]
    quaternion: tuple[float, float, float, float]


def stamped_pose(message: object, msgtype: str) -> StampedPose:
    """A decoded PoseStamped, PoseWithCovarianceStamped or Odometry (``POSE_TYPES``)."""
    pose = message.pose if msgtype == POSE_TYPES[0] else message.pose.pose  # type: ignore[attr-defined]
    child = normalise_frame(message.child_frame_id) if msgtype == POSE_TYPES[2] else ""  # type: ignore[attr-defined]
    return StampedPose(normalise_frame(message.header.frame_id), child, stamp_ns(message.header.stamp),  # type: ignore[attr-defined]
                       _vector(pose.position), _quaternion(pose.orientation))


def read_pose_topic(bag: BagFile, topic: str) -> tuple[Track, str | None]:
    """The topic's poses as a track (parent = the header frame), and Odometry's child frame if any."""
    track: Track | None = None
    child: str | None = None
    for ref, msgtype, raw in bag.scan([topic]):
        sample = stamped_pose(bag.deserialize(raw, msgtype, ref.topic), msgtype)
        if msgtype == POSE_TYPES[2]:
            child = sample.child or None
        if track is None:
            track = Track(sample.frame, child or "")
        track.add(sample.stamp_ns, sample.translation, sample.quaternion)
    if track is None:
        raise topic_error(bag, f"pose topic {topic} has no messages")
    return track, child


@dataclass
class PoseSource:
    """Camera-to-world of the camera frame at a stamp (None where the source does not reach)."""

    description: str
    tree: TransformTree
    camera_frame: str
    tolerance_ns: int
    fixed_frame: str | None = None  # TF: the world frame
    track: Track | None = None  # pose topic: the body's poses
    body_frame: str | None = None

    @property
    def world(self) -> str:
        """The frame the poses are in: the fixed frame, or the pose topic's header frame ('' if it names none)."""
        if self.track is None:
            assert self.fixed_frame is not None
            return self.fixed_frame
        return self.track.parent

    def at(self, stamp: int) -> np.ndarray | None:
        if self.track is None:
            return self.tree.lookup(self.world, self.camera_frame, stamp, self.tolerance_ns)
        body = self.track.at(stamp, self.tolerance_ns)
        return None if body is None else self.mounted(body, self.body_frame or self.camera_frame, stamp)

    def mounted(self, body_pose: np.ndarray, body: str, stamp: int) -> np.ndarray | None:
        """The camera's pose from ``body``'s (both in the world) through TF's body -> camera mounting at the stamp."""
        if body == self.camera_frame:
            return body_pose
        mount = self.tree.lookup(body, self.camera_frame, stamp, self.tolerance_ns)
        return None if mount is None else body_pose @ mount


def _tf_source(bag: BagFile, tree: TransformTree, camera: str, fixed: str, tolerance_ns: int) -> PoseSource:
    if fixed not in tree.frames:
        raise topic_error(bag, f"fixed frame {fixed!r} is not in TF (frames: {', '.join(sorted(tree.frames))})")
    if not tree.connected(fixed, camera):
        raise topic_error(bag, f"TF has no chain from {fixed!r} to the camera frame {camera!r}")
    chain = " -> ".join(reversed(tree.ancestors(camera)))
    return PoseSource(f"TF, {camera} in {fixed} (tree {chain})", tree, camera, tolerance_ns, fixed_frame=fixed)


def _topic_source(bag: BagFile, tree: TransformTree, camera: str, topic: str, options: BagOptions,
                  tolerance_ns: int) -> PoseSource:
    track, child = read_pose_topic(bag, topic)
    body = options.body_frame or child or camera
    if body != camera and not tree.connected(body, camera):
        raise topic_error(bag, f"{topic} gives the pose of {body!r} but TF has no chain from it to the camera "
                          f"frame {camera!r}; pass --body-frame if the poses are the camera's")
    mounted = "" if body == camera else f", through TF {body} -> {camera}"
    return PoseSource(f"{topic} ({bag.topics[topic].msgtype}), {body} in {track.parent or '(no frame)'}{mounted}",
                      tree, camera, tolerance_ns, track=track, body_frame=body)


def choose_pose_source(bag: BagFile, options: BagOptions, camera: str, tree: TransformTree) -> PoseSource:
    """The flagged pose source, else the only one the bag has."""
    tolerance_ns = round(options.pose_tolerance * 1e9)
    pose_topics = [topic for topic in of_types(bag, POSE_TYPES) if topic != options.corrected_topic]
    if options.pose_topic is not None and options.fixed_frame is not None:
        raise ValueError("--pose-topic and --fixed-frame are two pose sources; give one")
    if options.pose_topic is not None and options.pose_topic == options.corrected_topic:
        raise ValueError(f"--pose-topic and --corrected-topic both name {options.pose_topic}: the corrected "
                         "poses would be the poses the frames already have")
    if options.pose_topic is not None:
        if options.pose_topic not in pose_topics:
            raise topic_error(bag, f"--pose-topic {options.pose_topic} is not a PoseStamped, "
                              "PoseWithCovarianceStamped or Odometry topic with messages")
        return _topic_source(bag, tree, camera, options.pose_topic, options, tolerance_ns)
    if options.fixed_frame is not None:
        return _tf_source(bag, tree, camera, normalise_frame(options.fixed_frame), tolerance_ns)
    tf_moves = camera in tree.frames and tree.moves(tree.root(camera), camera)
    sources = ([f"TF ({tree.root(camera)} -> {camera})"] if tf_moves else []) + pose_topics
    if not sources:
        raise topic_error(bag, f"need exactly one pose source, found none (no pose topic, and no moving TF chain "
                          f"to the camera frame {camera!r})")
    if len(sources) > 1:
        raise topic_error(bag, f"need exactly one pose source, found {', '.join(sources)}")
    if tf_moves:
        return _tf_source(bag, tree, camera, tree.root(camera), tolerance_ns)
    return _topic_source(bag, tree, camera, pose_topics[0], options, tolerance_ns)
