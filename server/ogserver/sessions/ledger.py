"""The frames a session mapped, as CorrectPoses and Render address them: by sequence or by timestamp.

Each mapped frame is kept as its sequence, its timestamp (when the client sent one) and, for a keyframe, its
position in the mapper's keyframe list (the keyframe its anchors belong to). Frames skipped, refused or that
failed while mapping are not here: a correction naming one is refused as an unknown frame. Checkpoints keep
the ledger as one tensor (``TENSOR``), so a resumed session addresses the frames before its checkpoint too
(one from a checkpoint written before the ledger existed knows only the frames mapped after it).
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np
import torch

from ogmapping.frames.trajectory import KEY_TOLERANCE
from ogserver.api.validation import CorrectionEntry
from ogserver.errors import invalid

TENSOR = "session.mapped_frames"  # (n, 3) float64: sequence, keyframe position (-1: none), timestamp (NaN: none)
TIMESTAMP_TOLERANCE = KEY_TOLERANCE  # a timestamp names the mapped frame nearest it, this near (as TUM keys match)


@dataclass(frozen=True)
class Resolved:
    """A correction entry and the mapped frame it names."""

    field: str
    sequence: int
    keyframe: int | None  # its position in the mapper's keyframe list; None for a frame that is not a keyframe
    c2w: np.ndarray


class FrameLedger:
    def __init__(self) -> None:
        self._keyframes: dict[int, int | None] = {}  # sequence -> keyframe position
        self._times: list[tuple[float, int]] = []  # (timestamp, sequence), sorted
        self._stamps: dict[int, float] = {}

    def __len__(self) -> int:
        return len(self._keyframes)

    def add(self, sequence: int, timestamp: float | None, keyframe: int | None) -> None:
        self._keyframes[sequence] = keyframe
        if timestamp is not None:
            bisect.insort(self._times, (timestamp, sequence))
            self._stamps[sequence] = timestamp

    def _by_time(self, timestamp: float) -> int | None:
        """The sequence of the mapped frame nearest ``timestamp`` within the tolerance."""
        slot = bisect.bisect_left(self._times, (timestamp, -1))
        near = [self._times[i] for i in (slot - 1, slot) if 0 <= i < len(self._times)]
        best = min(near, key=lambda item: abs(item[0] - timestamp), default=None)
        return best[1] if best is not None and abs(best[0] - timestamp) <= TIMESTAMP_TOLERANCE else None

    def resolve(self, entries: list[CorrectionEntry]) -> list[Resolved]:
        """Each entry's mapped frame; INVALID_ARGUMENT naming the first entry that names none, or one named twice."""
        resolved, seen = [], {}
        for entry in entries:
            if entry.timestamp is not None:
                sequence = self._by_time(entry.timestamp)
                if sequence is None:
                    raise invalid(f"{entry.field}.timestamp", f"no mapped frame has timestamp {entry.timestamp!r} "
                                                              f"(within {TIMESTAMP_TOLERANCE:g} s)")
            else:
                sequence = entry.sequence
                if sequence not in self._keyframes:
                    raise invalid(f"{entry.field}.sequence", f"frame {sequence} is not a frame this session mapped")
            if sequence in seen:
                raise invalid(entry.field, f"names frame {sequence} again, as {seen[sequence]} did")
            seen[sequence] = entry.field
            resolved.append(Resolved(entry.field, sequence, self._keyframes[sequence], entry.c2w))
        return resolved

    def nearest_keyframe(self, sequence: int | None = None, timestamp: float | None = None) -> int | None:
        """The keyframe position of the mapped keyframe nearest a frame's ``sequence`` or ``timestamp`` (the
        earlier on a tie; the frame need not be one that was mapped), None while no keyframe is on record or
        for neither. INVALID_ARGUMENT for a timestamp where no keyframe carries one."""
        if sequence is None and timestamp is None:
            return None
        if timestamp is not None:
            stamped = [(abs(stamp - timestamp), self._keyframes[sequence], sequence)
                       for stamp, sequence in self._times if self._keyframes[sequence] is not None]
            if not stamped and self._keyframes:
                raise invalid("timestamp", "no mapped keyframe has a timestamp: name the frame by its sequence")
            return min(stamped)[1] if stamped else None
        keyframes = [(abs(mapped - sequence), mapped, position) for mapped, position in self._keyframes.items()
                     if position is not None]
        return min(keyframes)[2] if keyframes else None

    def tensor(self) -> torch.Tensor:
        rows = [(sequence, -1 if keyframe is None else keyframe, self._stamps.get(sequence, math.nan))
                for sequence, keyframe in self._keyframes.items()]
        return torch.tensor(rows, dtype=torch.float64).reshape(-1, 3)

    @classmethod
    def from_tensor(cls, rows: torch.Tensor | None) -> FrameLedger:
        """The ledger a checkpoint kept (none: empty); ValueError for a tensor of another shape."""
        ledger = cls()
        if rows is None:
            return ledger
        if rows.dim() != 2 or rows.shape[1] != 3:
            raise ValueError(f"{TENSOR} must have shape (n, 3), not {tuple(rows.shape)}")
        for sequence, keyframe, stamp in rows.tolist():
            ledger.add(int(sequence), None if math.isnan(stamp) else stamp, None if keyframe < 0 else int(keyframe))
        return ledger
