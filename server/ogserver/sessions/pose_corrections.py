"""A CorrectPoses batch applied to a session's map: all checked first, then all applied, or none.

Entries name mapped frames (``ledger.FrameLedger``); a keyframe's entry moves its anchors
(``Mapper.correct_poses``), a mapped frame that is not a keyframe is accepted and moves nothing (the map keeps no
pose of its own for it). A keyframe's corrected pose may not move its camera further than the server's
``limits.max_correction_metres`` and ``max_correction_degrees`` from the pose it has: that is a jump, not a
correction. The batch as applied, every entry by sequence, is what the recording keeps and a replay or a resume
applies again at the same point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from ogapi.v1 import mapping_pb2 as pb

from ogmapping.mapper import Mapper
from ogmapping.mapping.corrections import jump
from ogserver.errors import invalid
from ogserver.sessions.ledger import Resolved
from ogserver.settings import Limits


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
