"""A CorrectPoses batch applied to a session's map: all checked first, then all applied, or none.

Entries name mapped frames (``ledger.FrameLedger``); a keyframe's entry moves its anchors
(``Mapper.correct_poses``), a mapped frame that is not a keyframe is accepted and moves nothing (the map keeps no
pose of its own for it). A keyframe's corrected pose may not move its camera further than the server's
``limits.max_correction_metres`` and ``max_correction_degrees`` from the pose it has: that is a jump, not a
correction. The batch as applied, every entry by sequence, is what the recording keeps and a replay or a resume
applies again at the same point.
"""

from __future__ import annotations

import logging
from contextlib import suppress
from dataclasses import dataclass

import numpy as np
from ogapi.v1 import mapping_pb2 as pb

from ogmapping.mapper import Mapper
from ogmapping.mapping.corrections import jump
from ogserver.api import validation
from ogserver.api.validation import CorrectionEntry
from ogserver.errors import ServiceError, invalid
from ogserver.recording.disk import StorageError
from ogserver.recording.recorder import Recorder
from ogserver.sessions.backlog import RecordedCorrections
from ogserver.sessions.ledger import FrameLedger, Resolved
from ogserver.settings import Limits

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Applied:
    record: pb.PoseCorrections  # for the recording
    response: pb.CorrectPosesResponse


def _checked_jumps(mapper: Mapper, resolved: list[Resolved], limits: Limits) -> dict[int, np.ndarray]:
    """The keyframes' corrected poses by keyframe position; INVALID_ARGUMENT for the first jump beyond the bounds."""
    poses = mapper.keyframe_poses()
    corrected = {}
    for item in resolved:
        if item.keyframe is None:
            continue
        if item.keyframe >= len(poses):
            raise invalid(item.field, f"frame {item.sequence}'s keyframe is not in the map")
        metres, degrees = jump(np.asarray(poses[item.keyframe].client_c2w, dtype=np.float64), item.c2w)
        if metres > limits.max_correction_metres or degrees > limits.max_correction_degrees:
            raise invalid(f"{item.field}.c2w", f"moves frame {item.sequence}'s camera {metres:.3g} m and "
                                               f"{degrees:.3g} degrees, beyond the server's bounds of "
                                               f"{limits.max_correction_metres:g} m and "
                                               f"{limits.max_correction_degrees:g} degrees "
                                               "(limits.max_correction_metres, max_correction_degrees)")
        corrected[item.keyframe] = item.c2w
    return corrected


def apply(mapper: Mapper, resolved: list[Resolved], limits: Limits, after_sequence: int) -> Applied:
    """Check every entry, then move the map (the caller holds the session between two frames)."""
    corrected = _checked_jumps(mapper, resolved, limits)
    moved_anchors = 0
    if corrected:
        try:
            moved_anchors = mapper.correct_poses(corrected).anchors
        except ValueError as error:
            raise invalid("poses", error) from None
    record = pb.PoseCorrections(after_sequence=after_sequence, poses=[
        pb.CorrectedPose(sequence=item.sequence, c2w=item.c2w.reshape(-1).tolist()) for item in resolved])
    response = pb.CorrectPosesResponse(keyframes=len(corrected), frames=len(resolved) - len(corrected),
                                       anchors_moved=moved_anchors, after_sequence=after_sequence)
    return Applied(record, response)


@dataclass(frozen=True)
class Corrections:
    """A session's corrections: a client's batch applied and recorded, a recorded one applied again on resume.
    The caller holds the session between two frames."""

    session_id: str
    mapper: Mapper
    ledger: FrameLedger
    limits: Limits
    recorder: Recorder

    def live(self, entries: list[CorrectionEntry], after_sequence: int) -> pb.CorrectPosesResponse:
        if self.recorder.failure is not None:  # a correction the recording cannot keep would not replay
            raise self.recorder.failure
        applied = apply(self.mapper, self.ledger.resolve(entries), self.limits, after_sequence)
        with suppress(StorageError):  # logged by the recorder, which then refuses further frames
            self.recorder.write_corrections(applied.record)
        return applied.response

    def again(self, item: RecordedCorrections) -> None:
        """A recorded batch after the checkpoint; one a restarted server's tighter bounds refuse is logged."""
        try:
            entries = validation.pose_corrections(pb.CorrectPosesRequest(poses=item.message.poses),
                                                  len(item.message.poses))
            apply(self.mapper, self.ledger.resolve(entries), self.limits, item.message.after_sequence)
        except ServiceError as refusal:
            log.error("session %s: the pose corrections recorded after frame %d are refused on resume: %s",
                      self.session_id, item.message.after_sequence, refusal.message)
