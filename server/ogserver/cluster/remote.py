"""A session in a Ray actor, seen from a front-end: the ``HostedSession`` the servicer and stream use.

Every call is one actor call; a refusal raised in the actor (ServiceError) is raised again here as it
was, and an actor that no longer answers (its process or node died) is UNAVAILABLE. A frame stream
claims the actor's stream, offers one frame at a time (the offer waits while the session's queue is
full, so at most ``queue_depth`` frames are in flight to the actor) and a pump thread moves the
actor's acks, in order, into the stream's event queue.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any

import grpc
import ray
from ogapi.v1 import mapping_pb2 as pb
from ray import ObjectRef
from ray.actor import ActorHandle
from ray.exceptions import GetTimeoutError, RayActorError, RayTaskError

from ogmapping.queries import Rendered
from ogmapping.stats import MapStats
from ogserver.api.validation import RenderSpec
from ogserver.errors import ServiceError
from ogserver.sessions.counters import SessionCounters
from ogserver.sessions.stream_events import Acked, Lost, SessionClosed, StreamEvent

log = logging.getLogger(__name__)
EVENT_WAIT_SECONDS = 0.5  # how long one poll for acks waits in the actor; also how soon a finished pump stops
UNAVAILABLE = ("the session's Ray actor stopped answering (its process or node failed); the cluster restarts it "
               "from its last checkpoint: retry, and stream again from the frame after GetStats' last_index")
ACK_GROUP = "acks"  # the ack poll's own threads in the actor, apart from offers, renders and stats


def call(actor: ActorHandle, method: str, *args: Any, timeout: float | None = None, group: str = "") -> Any:
    """``actor.method(*args)``'s result (run in concurrency ``group`` when given); its ServiceError raised
    again, a dead actor as UNAVAILABLE."""
    bound = getattr(actor, method)
    pending = (bound.options(concurrency_group=group) if group else bound).remote(*args)
    return outcome(pending, method, timeout)


def outcome(pending: ObjectRef, what: str, timeout: float | None = None) -> Any:
    """The value of an actor call in flight, with ``call``'s errors."""
    try:
        return ray.get(pending, timeout=timeout)
    except RayTaskError as error:
        if isinstance(error.cause, ServiceError):
            raise error.cause from None
        raise
    except (RayActorError, GetTimeoutError) as error:
        log.warning("a session actor did not answer %s: %s", what, error)
        raise ServiceError(grpc.StatusCode.UNAVAILABLE, UNAVAILABLE) from None


class RemoteSession:
    def __init__(self, actor: ActorHandle, config: pb.SessionConfig, recording: Path) -> None:
        self.actor = actor
        self.id = config.session_id
        self.config = config
        self._recording = recording

    @property
    def recording(self) -> Path:
        return self._recording

    @property
    def streaming(self) -> bool:
        return call(self.actor, "streaming")

    @contextmanager
    def stream(self, sink: queue.SimpleQueue[StreamEvent]) -> Iterator[None]:
        call(self.actor, "claim_stream")
        stop = threading.Event()
        pump = threading.Thread(target=self._pump, args=(sink, stop), name=f"pump-{self.id[:8]}", daemon=True)
        pump.start()
        try:
            yield
        finally:
            stop.set()
            with suppress(ServiceError):  # an actor that died holds no stream any more
                call(self.actor, "release_stream")  # which also ends the pump's poll in flight
            pump.join()

    def _pump(self, sink: queue.SimpleQueue[StreamEvent], stop: threading.Event) -> None:
        while not stop.is_set():
            try:
                events = call(self.actor, "events", EVENT_WAIT_SECONDS, group=ACK_GROUP)
            except ServiceError as error:
                sink.put(Lost(error))
                return
            for kind, data in events:
                sink.put(Acked(pb.FrameAck.FromString(data)) if kind == "ack" else SessionClosed())

    def offer(self, message: pb.Frame, max_pixels: int, sink: queue.SimpleQueue[StreamEvent] | None) -> bool:
        """The actor validates and queues the frame; its acks reach ``sink`` through the stream's pump."""
        return call(self.actor, "offer", message.SerializeToString(), max_pixels)

    def count_rejected(self) -> None:
        call(self.actor, "count_rejected")

    def render(self, spec: RenderSpec) -> Rendered:
        return call(self.actor, "render", spec)

    def map_stats(self) -> MapStats:
        return call(self.actor, "map_stats")

    def counters(self) -> SessionCounters:
        return call(self.actor, "counters")

    def snapshot(self) -> bytes:
        return call(self.actor, "snapshot")

    def correct_poses(self, message: pb.CorrectPosesRequest) -> pb.CorrectPosesResponse:
        return pb.CorrectPosesResponse.FromString(call(self.actor, "correct_poses", message.SerializeToString()))
