"""A frame stream that survives its server going away: on UNAVAILABLE, wait, ask GetStats where the
session stands, and stream again from the frame after the last one it holds.

UNAVAILABLE is what a stream gets when the server process or, in cluster mode, the node holding the
session failed; the session comes back (a restarted server or a restarted Ray actor resumes it from its
checkpoint and recording) with the same id and token. GetStats' ``last_index`` is the ``Frame.index``
of the last frame the session holds, so a client whose indices increase sends those after it: nothing
is mapped twice and no frame the session acknowledged is sent again. Waits grow (0.5 s, 1 s, 2 s, ...
up to ``longest``) and are bounded in number; any other error ends the stream at once.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass

import grpc
from ogapi.v1 import mapping_pb2 as pb
from ogapi.v1 import mapping_pb2_grpc as pb_grpc

from ogclient.connection import ClientError, SessionRef, describe
from ogclient.streaming import StreamResult, stream_frames

# The frames to send given the Frame.index of the last one the session holds (None: it holds none).
Source = Callable[[int | None], Iterable[pb.Frame]]


@dataclass(frozen=True)
class Backoff:
    retries: int = 8  # UNAVAILABLE answers tolerated with no frame acknowledged in between
    first: float = 0.5  # seconds before the first retry; doubled for each next one
    longest: float = 15.0

    def wait(self, attempt: int) -> float:
        return min(self.first * 2**attempt, self.longest)


class Unavailable:
    """Counts UNAVAILABLE answers since the last acknowledged frame and sleeps between them; past ``retries``,
    the final error."""

    def __init__(self, backoff: Backoff, say: Callable[[str], None]) -> None:
        self.backoff = backoff
        self.say = say
        self.attempt = 0
        self.since = time.monotonic()

    def retry(self, error: grpc.RpcError, what: str) -> None:
        if error.code() != grpc.StatusCode.UNAVAILABLE:
            raise error
        if self.attempt >= self.backoff.retries:
            raise ClientError(
                f"{what}: the server stayed unavailable through {self.backoff.retries} retries over "
                f"{time.monotonic() - self.since:.0f} s ({describe(error)}); the frames it acknowledged are in the "
                "session: `ogclient stream --resume --session FILE` goes on from there later") from None
        delay = self.backoff.wait(self.attempt)
        self.attempt += 1
        self.say(f"{what}: {describe(error)}; retry {self.attempt} of {self.backoff.retries} in {delay:g} s")
        time.sleep(delay)

    def progressed(self) -> None:
        self.attempt = 0
        self.since = time.monotonic()


def standing(stub: pb_grpc.MappingStub, session: SessionRef, unavailable: Unavailable) -> pb.Stats:
    """GetStats once the session answers again (while its host restarts it is UNAVAILABLE)."""
    while True:
        try:
            return stub.GetStats(pb.GetStatsRequest(session_id=session.session_id), metadata=session.metadata())
        except grpc.RpcError as error:
            unavailable.retry(error, "GetStats")


def stream_resuming(
    stub: pb_grpc.MappingStub, session: SessionRef, source: Source, total: int | None = None, progress: bool = True,
    backoff: Backoff | None = None, say: Callable[[str], None] = print,
) -> StreamResult:
    """Stream ``source(None)``; after each cut by UNAVAILABLE, stream ``source(last_index)`` once GetStats
    answers. The result holds every ack received, across the streams."""
    result = StreamResult()
    unavailable = Unavailable(backoff or Backoff(), say)
    last_index: int | None = None
    while True:
        before = len(result.acks)
        try:
            return stream_frames(stub, session, source(last_index), total if last_index is None else None, progress,
                                 result)
        except grpc.RpcError as error:
            if len(result.acks) > before:
                unavailable.progressed()
            unavailable.retry(error, "the frame stream was cut")
        stats = standing(stub, session, unavailable)
        last_index = stats.last_index if stats.last_sequence else None
        say(f"resuming: the session holds {stats.last_sequence} frames"
            + (f", the last with index {stats.last_index}" if last_index is not None else "")
            + "; streaming the frames after it")
