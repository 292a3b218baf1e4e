"""What a frame stream's response loop waits on: acks from the session, and the ends of the stream."""

from __future__ import annotations

from dataclasses import dataclass

from ogapi.v1 import mapping_pb2 as pb

from ogserver.errors import ServiceError


@dataclass(frozen=True)
class Acked:
    """The session's answer to an accepted frame (mapped, or failed while mapping): one of those the stream owes."""

    ack: pb.FrameAck


@dataclass(frozen=True)
class Rejected:
    """The error ack of a frame refused before it reached the queue."""

    ack: pb.FrameAck


@dataclass(frozen=True)
class ReaderDone:
    """The client half-closed (or the reader stopped on ``error``) after ``accepted`` frames were queued."""

    accepted: int
    error: ServiceError | None = None


@dataclass(frozen=True)
class Cancelled:
    """The call ended from the client's side."""


@dataclass(frozen=True)
class SessionClosed:
    """The session was closed while the stream was open."""


@dataclass(frozen=True)
class Lost:
    """The session's host stopped answering (cluster mode: its actor or its node died)."""

    error: ServiceError


StreamEvent = Acked | Rejected | ReaderDone | Cancelled | SessionClosed | Lost
