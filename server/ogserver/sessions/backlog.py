"""What a crashed session's recording holds after its checkpoint: the frames a resume maps again.

The recording names its session (its first message, the ``SessionConfig``), so a recording copied
under another session's name is refused rather than mapped into that session's map. Its acks say
which frames a realtime session skipped: those stay skipped, and the resumed session maps only what
the live one mapped (or was mapping: a frame whose ack the crash lost is mapped again). Pose corrections
recorded after the checkpoint's frame are applied again after the frame they followed (a checkpoint holds the
corrections applied up to its frame's checkpoint, and none applied after it: ``session.py``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from google.protobuf.message import DecodeError
from ogapi import recording as layout
from ogapi.v1 import mapping_pb2 as pb

from ogserver.recording.checkpoint import Position


@dataclass(frozen=True)
class Recorded:
    """A frame the recording already holds, mapped again by a resumed session."""

    sequence: int
    message: pb.Frame


@dataclass(frozen=True)
class RecordedCorrections:
    """A CorrectPoses batch the recording holds, applied again by a resumed session."""

    message: pb.PoseCorrections


@dataclass
class RecordedAfter:
    session_id: str = ""  # as the recording's first message says
    frames: int = 0  # recorded frames in all
    last: Position | None = None  # the last recorded frame, if after the checkpoint
    frames_after: list[Recorded] = field(default_factory=list)  # those after the checkpoint
    skipped: set[int] = field(default_factory=set)  # sequences of the frames acknowledged as skipped
    corrections_after: list[RecordedCorrections] = field(default_factory=list)  # applied after the checkpoint

    def backlog(self) -> list[Recorded | RecordedCorrections]:
        """The frames after the checkpoint that the live session did not skip, each correction batch before the
        first frame after the one it followed."""
        items: list[Recorded | RecordedCorrections] = []
        corrections = list(self.corrections_after)
        for item in self.frames_after:
            while corrections and corrections[0].message.after_sequence < item.sequence:
                items.append(corrections.pop(0))
            if item.sequence not in self.skipped:
                items.append(item)
        return items + corrections


def read_after(recording: Path, sequence: int) -> RecordedAfter:
    """The recording's session id, frame count and the frames after ``sequence``; RecordingError if damaged."""
    result = RecordedAfter()
    topics = {layout.TOPIC_SESSION, layout.TOPIC_FRAMES, layout.TOPIC_ACKS, layout.TOPIC_CORRECTIONS}
    for item in layout.read_messages(recording, topics):
        try:
            if item.topic == layout.TOPIC_SESSION:
                result.session_id = result.session_id or pb.SessionConfig.FromString(item.data).session_id
            elif item.topic == layout.TOPIC_FRAMES:
                result.frames += 1
                if result.frames > sequence:
                    message = pb.Frame.FromString(item.data)
                    result.frames_after.append(Recorded(result.frames, message))
                    result.last = Position(result.frames, message.index)
            elif item.topic == layout.TOPIC_CORRECTIONS:
                corrections = pb.PoseCorrections.FromString(item.data)
                if corrections.after_sequence >= sequence:
                    result.corrections_after.append(RecordedCorrections(corrections))
            else:
                ack = pb.FrameAck.FromString(item.data)
                if ack.skipped and ack.sequence > sequence:
                    result.skipped.add(ack.sequence)
        except DecodeError:
            raise layout.RecordingError(f"{recording.name}: a damaged {item.topic} message") from None
    return result
