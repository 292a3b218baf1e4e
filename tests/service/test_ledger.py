"""The frames a session mapped, as pose corrections name them: nearest timestamp within the TUM tolerance,
sequences of mapped frames only, and the ledger a checkpoint keeps; and the keyframe nearest any frame, as a
render at a client pose of a frame's time needs it."""

from __future__ import annotations

import numpy as np
import pytest
from ogserver.api.validation import CorrectionEntry
from ogserver.errors import ServiceError
from ogserver.sessions.ledger import TIMESTAMP_TOLERANCE, FrameLedger


def entry(sequence: int | None = None, timestamp: float | None = None, field: str = "poses[0]") -> CorrectionEntry:
    return CorrectionEntry(field, sequence, timestamp, np.eye(4))


def ledger() -> FrameLedger:
    frames = FrameLedger()
    frames.add(1, 1000.0, 0)
    frames.add(2, 1000.033, None)
    frames.add(4, None, 1)  # sent without a timestamp; sequence 3 was skipped
    return frames


def test_timestamps_name_the_nearest_mapped_frame_within_the_tolerance() -> None:
    resolved = ledger().resolve([entry(timestamp=1000.033 + TIMESTAMP_TOLERANCE / 2), entry(timestamp=999.99999)])
    assert [(item.sequence, item.keyframe) for item in resolved] == [(2, None), (1, 0)]
    with pytest.raises(ServiceError, match=r"poses\[0\].timestamp: no mapped frame has timestamp 1000.01"):
        ledger().resolve([entry(timestamp=1000.01)])


def test_sequences_name_mapped_frames_only_and_once() -> None:
    assert [item.keyframe for item in ledger().resolve([entry(sequence=4)])] == [1]
    with pytest.raises(ServiceError, match=r"poses\[0\].sequence: frame 3 is not a frame this session mapped"):
        ledger().resolve([entry(sequence=3)])
    with pytest.raises(ServiceError, match=r"poses\[1\]: names frame 1 again, as poses\[0\] did"):
        ledger().resolve([entry(sequence=1), entry(timestamp=1000.0, field="poses[1]")])


def test_a_checkpoint_keeps_the_ledger() -> None:
    kept = FrameLedger.from_tensor(ledger().tensor())
    assert len(kept) == 3
    assert [item.sequence for item in kept.resolve([entry(timestamp=1000.033), entry(sequence=4, field="b")])] == [2, 4]
    assert len(FrameLedger.from_tensor(None)) == 0


def test_a_render_names_the_keyframe_nearest_its_frame() -> None:
    frames = ledger()
    frames.add(9, 1000.3, 2)
    assert [frames.nearest_keyframe(sequence=n) for n in (1, 2, 3, 4, 6, 7, 100)] == [0, 0, 1, 1, 1, 2, 2]
    assert [frames.nearest_keyframe(timestamp=t) for t in (0.0, 1000.1, 1000.2, 5000.0)] == [0, 0, 2, 2]
    assert FrameLedger().nearest_keyframe(sequence=5) is None and frames.nearest_keyframe() is None
    assert FrameLedger().nearest_keyframe(timestamp=5.0) is None
    unstamped = FrameLedger()
    unstamped.add(1, None, 0)
    with pytest.raises(ServiceError, match="timestamp: no mapped keyframe has a timestamp"):
        unstamped.nearest_keyframe(timestamp=1.0)
    assert FrameLedger.from_tensor(frames.tensor()).nearest_keyframe(sequence=7) == 2
