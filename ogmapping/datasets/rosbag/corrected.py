"""A SLAM system's corrected trajectory read from a topic of the bag (``--corrected-topic``), as the frames' poses.

A SLAM system that closes a loop publishes its corrected trajectory: a nav_msgs/Path, each message the whole
trajectory so far with every pose stamped (the last message is the latest, and the one read), or a stream of
PoseStamped, PoseWithCovarianceStamped or Odometry, each message one corrected pose (a later one at the same
stamp replaces an earlier one). Each pose is read as a pose topic's are (``poses``), so that a corrected pose
equal to the one a frame was given is that pose: the pose of a body frame in the header's frame, the body being
``--body-frame``, else Odometry's ``child_frame_id``, else the pose source's body (the camera itself for TF and
for a PoseStamped pose topic), the camera mounted on it through TF at the pose's stamp. The header's frame must
be the frames' world (the fixed frame, or the pose topic's header frame); an empty one is taken as it. The
trajectory is keyed by stamp in seconds, as the frames' timestamps are.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ogmapping.datasets.rosbag.bagfile import BagFile
from ogmapping.datasets.rosbag.headers import normalise_frame
from ogmapping.datasets.rosbag.poses import PoseSource, StampedPose, stamped_pose
from ogmapping.datasets.rosbag.topics import POSE_TYPES, topic_error
from ogmapping.frames.camera import validate_pose
from ogmapping.frames.rotation import quaternion_pose
from ogmapping.frames.trajectory import Trajectory

PATH = "nav_msgs/msg/Path"
CORRECTED_TYPES = (PATH, *POSE_TYPES)


@dataclass(frozen=True)
class Corrected:
    """The corrected camera-to-world poses, and what was read, for the bag's report."""

    trajectory: Trajectory
    description: str


def _samples(bag: BagFile, topic: str) -> tuple[list[StampedPose], str]:
    """The topic's corrected poses in bag order, and which messages held them."""
    entry = bag.topics.get(topic)
    if entry is None:
        raise topic_error(bag, f"--corrected-topic {topic} is not in the bag")
    if entry.msgtype not in CORRECTED_TYPES:
        raise topic_error(bag, f"--corrected-topic {topic} is a {entry.msgtype} topic; a corrected trajectory is "
                          f"one of {', '.join(CORRECTED_TYPES)}")
    samples: list[StampedPose] = []
    count, last = 0, None
    for ref, msgtype, raw in bag.scan([topic]):  # a Path is decoded once, the last; pose messages each
        count += 1
        if msgtype == PATH:
            last = (ref, msgtype, raw)
        else:
            samples.append(stamped_pose(bag.deserialize(raw, msgtype, ref.topic), msgtype))
    if not count:
        raise topic_error(bag, f"--corrected-topic {topic} ({entry.msgtype}) has no messages")
    if last is None:
        return samples, f"{count} messages"
    ref, msgtype, raw = last
    path = bag.deserialize(raw, msgtype, ref.topic)
    frame = normalise_frame(path.header.frame_id)  # type: ignore[attr-defined]
    for item in path.poses:  # type: ignore[attr-defined]
        sample = stamped_pose(item, POSE_TYPES[0])
        samples.append(sample if sample.frame else replace(sample, frame=frame))
    if not samples:
        raise topic_error(bag, f"--corrected-topic {topic} ({entry.msgtype}): its last message holds no poses")
    return samples, f"the last of {count} messages"


def read_corrected(bag: BagFile, topic: str, source: PoseSource, body_frame: str | None) -> Corrected:
    """The topic's corrected poses as the camera's, converted as ``source`` converts the frames' (``body_frame``:
    the ``--body-frame`` flag). Poses TF cannot mount the camera on at their stamp are left out."""
    samples, read = _samples(bag, topic)
    camera, world = source.camera_frame, source.world
    by_stamp: dict[int, np.ndarray] = {}
    bodies: set[str] = set()
    unmounted = 0
    for sample in samples:
        if sample.frame and world and sample.frame != world:
            raise topic_error(bag, f"--corrected-topic {topic} gives poses in {sample.frame!r}, the frames' poses "
                              f"are in {world!r} ({source.description})")
        body = body_frame or sample.child or source.body_frame or camera
        if body != camera and not source.tree.connected(body, camera):
            raise topic_error(bag, f"--corrected-topic {topic} gives the pose of {body!r} but TF has no chain from "
                              f"it to the camera frame {camera!r}; pass --body-frame if the poses are the camera's")
        c2w = source.mounted(quaternion_pose(sample.translation, sample.quaternion), body, sample.stamp_ns)
        if c2w is None:
            unmounted += 1
            continue
        by_stamp[sample.stamp_ns] = validate_pose(c2w, f"{topic}: the corrected pose at {sample.stamp_ns} ns")
        bodies.add(body)
    if not by_stamp:
        raise topic_error(bag, f"--corrected-topic {topic}: TF mounts the camera on none of its {len(samples)} poses "
                          f"within {source.tolerance_ns * 1e-9:g} s of their stamps")
    stamps = sorted(by_stamp)
    keys = np.array([stamp * 1e-9 for stamp in stamps])  # as the frames' timestamps are computed
    trajectory = Trajectory(keys, np.stack([by_stamp[stamp] for stamp in stamps]), topic)
    mounts = ", ".join(f"{body} -> {camera}" for body in sorted(bodies) if body != camera)
    description = (f"{topic} ({bag.topics[topic].msgtype}, {read}): {len(stamps)} poses of "
                   f"{', '.join(sorted(bodies))} in {world or '(no frame)'}"
                   + (f", through TF {mounts}" if mounts else "")
                   + (f"; {unmounted} left out, TF not mounting the camera at their stamps" if unmounted else ""))
    return Corrected(trajectory, description)
