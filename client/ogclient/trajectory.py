"""Camera trajectories from a session's acks or recording, written in TUM format.

A session that refines poses (``poses.refine``) answers each mapped frame with its refined pose
(``FrameAck.pose_correction.refined_c2w``); the recording keeps those acks beside the frames, so both
the client's trajectory and the refined one can be written from it. Each line is keyed as
``ogmapping.frames.trajectory`` keys frames: the frame's timestamp, else its index.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from ogapi.recording import Recording
from ogapi.v1 import mapping_pb2 as pb

from ogclient.connection import ClientError
from ogmapping.frames.trajectory import write_tum


@dataclass(frozen=True)
class Poses:
    """Keyed camera-to-world poses in the order the session mapped them."""

    keys: list[float]
    poses: list[np.ndarray]

    def write(self, path: str | Path, comment: str) -> None:
        write_tum(path, self.keys, self.poses, [comment])


def frame_key(message: pb.Frame) -> float:
    """The frame's key in a TUM file: its timestamp, else its index."""
    return float(message.timestamp) if message.HasField("timestamp") else float(message.index)


def matrix(numbers: Iterable[float]) -> np.ndarray:
    return np.array(list(numbers), dtype=np.float64).reshape(4, 4)


def refined_poses(keys: dict[int, float], acks: Iterable[pb.FrameAck]) -> Poses:
    """The refined pose of every ack that carries one, keyed by ``keys`` (Frame.index -> key)."""
    corrected = [ack for ack in acks if ack.HasField("pose_correction")]
    return Poses([keys[ack.index] for ack in corrected], [matrix(ack.pose_correction.refined_c2w) for ack in corrected])


def from_recording(recorded: Recording, path: str | Path, client: bool) -> Poses:
    """The client's pose of every recorded frame (``client``), or the refined pose of every frame whose
    recorded ack carries one (matched by its sequence: the recorded frames in order, from 1)."""
    if client:
        frames = [frame for _, frame in recorded.frames]
        return Poses([frame_key(frame) for frame in frames], [matrix(frame.c2w) for frame in frames])
    poses = Poses([], [])
    for ack in recorded.acks:
        if not ack.HasField("pose_correction"):
            continue
        if not 1 <= ack.sequence <= len(recorded.frames) or recorded.frames[ack.sequence - 1][1].index != ack.index:
            raise ClientError(f"{path}: the ack of frame {ack.index} (sequence {ack.sequence}) matches no recorded "
                              "frame")
        poses.keys.append(frame_key(recorded.frames[ack.sequence - 1][1]))
        poses.poses.append(matrix(ack.pose_correction.refined_c2w))
    if not poses.keys:
        raise ClientError(f"{path}: no refined poses: the recorded session did not refine poses (poses.refine); "
                          "--client writes the client's")
    return poses
