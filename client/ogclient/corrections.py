"""Pose corrections sent to a session (CorrectPoses): from a TUM trajectory, and again from a recording.

A SLAM system that closes a loop publishes its corrected trajectory; ``correct-poses`` sends it in batches,
each line naming a mapped frame by its timestamp (the first column, as the frames carried it) or by its
FrameAck.sequence. The server applies each batch whole or not at all: a batch it refuses leaves the batches
before it applied. A replay streams a recording's frames in segments, each batch of corrections sent once the
frames before it are mapped, so the replayed map takes them at the point the recorded one did.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

from ogapi.recording import Recording
from ogapi.v1 import mapping_pb2 as pb
from ogapi.v1 import mapping_pb2_grpc as pb_grpc

from ogclient.connection import ClientError, SessionRef
from ogmapping.frames.trajectory import Trajectory

DEFAULT_BATCH = 1000  # well within the server's default limits.max_pose_corrections (10000)


def entries(trajectory: Trajectory, keys: str) -> list[pb.CorrectedPose]:
    """One entry a pose, keyed by ``keys`` ("timestamp" or "sequence": the file's first column)."""
    poses = []
    for key, c2w in zip(trajectory.keys, trajectory.poses, strict=True):
        if keys == "sequence":
            if key < 1 or key != int(key):
                raise ClientError(f"{trajectory.name}: {key!r} is not a frame sequence (a whole number from 1)")
            poses.append(pb.CorrectedPose(sequence=int(key), c2w=c2w.reshape(-1).tolist()))
        else:
            poses.append(pb.CorrectedPose(timestamp=float(key), c2w=c2w.reshape(-1).tolist()))
    return poses


def for_mapped(trajectory: Trajectory, keys: dict[int, float], acks: list[pb.FrameAck]) -> list[pb.CorrectedPose]:
    """The trajectory's poses of the frames this stream had mapped, each by its sequence: ``keys`` maps each
    sent frame's index to its key (its timestamp, else its index), as a TUM file keys it."""
    poses = []
    for ack in acks:
        if not ack.accepted or ack.skipped or ack.index not in keys:
            continue
        c2w = trajectory.find(keys[ack.index])
        if c2w is not None:
            poses.append(pb.CorrectedPose(sequence=ack.sequence, c2w=c2w.reshape(-1).tolist()))
    return poses


@dataclass
class Sent:
    batches: int = 0
    keyframes: int = 0
    frames: int = 0
    anchors_moved: int = 0

    def summary(self) -> str:
        return (f"{self.batches} batches applied: {self.keyframes} keyframes corrected ({self.anchors_moved} anchors "
                f"moved), {self.frames} other mapped frames (no pose of their own in the map)")


def send(stub: pb_grpc.MappingStub, session: SessionRef, poses: list[pb.CorrectedPose], batch: int) -> Sent:
    """``poses`` in batches of ``batch``; a refused batch raises (grpc.RpcError) with the batches before it applied."""
    sent = Sent()
    for start in range(0, len(poses), batch):
        request = pb.CorrectPosesRequest(session_id=session.session_id, poses=poses[start:start + batch])
        response = stub.CorrectPoses(request, metadata=session.metadata())
        sent.batches += 1
        sent.keyframes += response.keyframes
        sent.frames += response.frames
        sent.anchors_moved += response.anchors_moved
    return sent


@dataclass(frozen=True)
class Segment:
    """Recorded frames [start, end) (list positions), then the correction batch applied after them, if any."""

    start: int
    end: int
    corrections: pb.PoseCorrections | None


def segments(recording: Recording) -> Iterator[Segment]:
    """The recording's frames cut where its corrections were applied (after frame ``after_sequence``: the
    n-th recorded frame has sequence n)."""
    start, total = 0, len(recording.frames)
    for batch in recording.corrections:
        end = min(max(int(batch.after_sequence), start), total)
        yield Segment(start, end, batch)
        start = end
    if start < total or not recording.corrections:
        yield Segment(start, total, None)
