"""What ``ogmap run`` reports of pose refinement (``poses.refine``): each streamed frame's pose as
given and as refined, written as a TUM trajectory, and, against an exact trajectory
(``--eval-poses``), how far each lies from the truth."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ogmapping.frames.frame import Frame
from ogmapping.frames.trajectory import Trajectory, frame_key, pose_errors, write_tum
from ogmapping.mapper import FrameResult
from ogmapping.queries import KeyframePose, in_map_frame, nearest


@dataclass
class PoseLog:
    """Streamed frames' given and refined poses, in streaming order."""

    indices: list[int] = field(default_factory=list)
    keys: list[float] = field(default_factory=list)
    given: list[np.ndarray] = field(default_factory=list)
    refined: list[np.ndarray] = field(default_factory=list)
    clamped: list[bool] = field(default_factory=list)

    def add(self, frame: Frame, result: FrameResult) -> None:
        self.indices.append(frame.index)
        self.keys.append(frame_key(frame))
        self.given.append(np.asarray(frame.c2w, dtype=np.float64))
        self.refined.append(result.pose.refined_c2w)
        self.clamped.append(result.pose.clamped)

    def settle(self, keyframes: list[KeyframePose], follow_nearest: bool = False) -> None:
        """Keyframes go on being refined after their own frame: take their final poses. With ``follow_nearest``
        (streamed frames have no correction of their own: keyframe poses alone are refined) every other frame's
        pose is moved as the keyframe nearest it was, as renders of its time are (``Mapper.render``)."""
        final = {pose.index: pose.refined_c2w for pose in keyframes}
        indices = [pose.index for pose in keyframes]

        def settled(index: int, given: np.ndarray, refined: np.ndarray) -> np.ndarray:
            if index in final:
                return final[index]
            if not follow_nearest or not keyframes:
                return refined
            return in_map_frame(keyframes[nearest(indices, index)], given)

        self.refined = [settled(index, given, refined)
                        for index, given, refined in zip(self.indices, self.given, self.refined, strict=True)]

    def write(self, path: Path) -> None:
        write_tum(path, self.keys, self.refined, ["refined camera-to-world poses of the streamed frames"])

    def summary(self, truth: Trajectory | None) -> dict:
        """Mean and largest correction, frames clamped, and with ``truth`` the given and refined poses'
        errors against it (means, and per frame for plotting)."""
        corrections_m, corrections_deg = pose_errors(np.array(self.refined), np.array(self.given))
        report = {
            "mean_correction_cm": 100 * float(corrections_m.mean()),
            "max_correction_cm": 100 * float(corrections_m.max()),
            "mean_correction_deg": float(corrections_deg.mean()),
            "max_correction_deg": float(corrections_deg.max()),
            "clamped_frames": int(sum(self.clamped)),
        }
        per_frame = {"index": self.indices, "correction_cm": (100 * corrections_m).tolist(),
                     "correction_deg": corrections_deg.tolist()}
        if truth is not None:
            exact = np.array([truth.find(key) for key in self.keys])
            for name, poses in (("given", self.given), ("refined", self.refined)):
                metres, degrees = pose_errors(np.array(poses), exact)
                report[f"{name}_error_cm"] = 100 * float(metres.mean())
                report[f"{name}_error_deg"] = float(degrees.mean())
                per_frame[f"{name}_error_cm"] = (100 * metres).tolist()
        return {**report, "per_frame": per_frame}
