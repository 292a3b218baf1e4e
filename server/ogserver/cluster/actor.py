"""A session's Ray actor: a ``Registry`` holding exactly one ``Session``, the single server's code unchanged.

Its methods answer in plain values, protobuf bytes and the engine's dataclasses; refusals are the
registry's ``ServiceError`` (``remote.py`` raises them again on the front-end). The actor is threaded
(Ray ``max_concurrency``): a frame offer waiting on the session's bounded queue, the stream's event
poll and renders run side by side, as the gRPC threads of a single server would. When Ray restarts
the actor after its process or node died, the session's checkpoint is still on the shared record
dir: the new actor resumes the session from it as a restarted single server would
(``Registry.resume``: same id and token, the recorded frames after the checkpoint mapped again).
"""

from __future__ import annotations

import logging
import os
import queue
from contextlib import ExitStack

import grpc
import ray
from ogapi.v1 import mapping_pb2 as pb
from ray.actor import ActorHandle

from ogmapping.queries import Rendered
from ogmapping.runtime.profile import resolve_device
from ogmapping.stats import MapStats
from ogserver import LOG_FORMAT
from ogserver.api.validation import RenderSpec
from ogserver.errors import ServiceError
from ogserver.recording import checkpoint
from ogserver.sessions.counters import SessionCounters
from ogserver.sessions.hosting import Closed, Opened, Upload
from ogserver.sessions.registry import Registry
from ogserver.sessions.session import Session
from ogserver.sessions.stream_events import Acked, Cancelled, SessionClosed, StreamEvent
from ogserver.settings import Settings

Described = tuple[bytes, str]  # the session's SessionConfig, serialized, and its recording's path
Event = tuple[str, bytes]  # ("ack", FrameAck bytes) or ("closed", b"")


class SessionActor:
    def __init__(self, settings: Settings, session_id: str, directory: ActorHandle) -> None:
        # Before numba's first parallel kernel: the session's worker and renders run kernels concurrently.
        os.environ.setdefault("NUMBA_THREADING_LAYER", "threadsafe")
        # The registry's and session's log lines, in the worker's log (Ray's logs/worker-*.err on its node).
        logging.basicConfig(level=logging.INFO, format=LOG_FORMAT)
        import torch

        torch.set_num_threads(max(1, int(settings.session_cpus)))
        self._registry = Registry(settings, str(resolve_device(settings.device)))
        self._session: Session | None = None
        self._sink: queue.SimpleQueue[StreamEvent] | None = None
        self._stream = ExitStack()
        recording = self._registry.record_dir / f"{session_id}.mcap"
        if self._registry.store is not None:  # this node's scratch space may not hold the session's latest files
            self._registry.store.fetch(session_id, self._registry.record_dir)
        if checkpoint.path_for(recording).exists():  # Ray restarted the actor: its process or node died
            self._session = self._registry.resume(recording)
        directory.placed.remote(session_id, self.node_id())  # the directory counts sessions per node

    def _opened(self, opened: Opened) -> tuple[bytes, str, str]:
        assert isinstance(opened.session, Session)
        self._session = opened.session
        return opened.session.config.SerializeToString(), opened.token, str(opened.session.recording)

    def open(self, request: bytes, owner: str, session_id: str) -> tuple[bytes, str, str]:
        """Create the session: (its SessionConfig bytes, its token, its recording)."""
        return self._opened(self._registry.create(pb.CreateSessionRequest.FromString(request), owner, session_id))

    def restore(self, owner: str, upload: Upload, session_id: str) -> tuple[bytes, str, str]:
        return self._opened(self._registry.restore(owner, lambda: upload, session_id))

    def _current(self) -> Session:
        if self._session is None:
            raise ServiceError(grpc.StatusCode.NOT_FOUND, "the session is closed")
        return self._session

    @staticmethod
    def node_id() -> str:
        """The Ray node this actor runs on (logged where a session opens; the tests find its node by it)."""
        return ray.get_runtime_context().get_node_id()

    def describe(self) -> Described:
        session = self._current()
        return session.config.SerializeToString(), str(session.recording)

    def authorize(self, token: str) -> Described:
        """The registry's own lookup: the token checked against the stored hash, the session touched."""
        self._registry.get(self._current().id, token)
        return self.describe()

    def touch(self) -> None:
        self._registry.touch(self._current())

    # ------------------------------------------------------------------ the frame stream

    def claim_stream(self) -> None:
        sink: queue.SimpleQueue[StreamEvent] = queue.SimpleQueue()
        self._stream.enter_context(self._current().stream(sink))
        self._sink = sink

    def release_stream(self) -> None:
        sink, self._sink = self._sink, None
        self._stream.close()
        if sink is not None:
            sink.put(Cancelled())  # wakes the poll waiting on it, which returns what it has

    def streaming(self) -> bool:
        return self._session is not None and self._session.streaming

    def offer(self, message: bytes, max_pixels: int) -> bool:
        """Validate and queue one frame, waiting while the session's queue is full (backpressure)."""
        return self._current().offer(pb.Frame.FromString(message), max_pixels, self._sink)

    def count_rejected(self) -> None:
        self._current().count_rejected()

    def events(self, wait: float) -> list[Event]:
        """The stream's acks and its end, in order, waiting up to ``wait`` seconds for the first."""
        sink = self._sink
        if sink is None:
            return []
        taken = []
        try:
            taken.append(sink.get(timeout=wait))
            while True:
                taken.append(sink.get_nowait())
        except queue.Empty:
            pass
        return [("ack", event.ack.SerializeToString()) if isinstance(event, Acked) else ("closed", b"")
                for event in taken if isinstance(event, Acked | SessionClosed)]

    # ------------------------------------------------------------------ queries

    def render(self, spec: RenderSpec) -> Rendered:
        return self._current().render(spec)

    def map_stats(self) -> MapStats:
        return self._current().map_stats()

    def counters(self) -> SessionCounters:
        return self._current().counters()

    def snapshot(self) -> bytes:
        return self._current().snapshot()

    def correct_poses(self, message: bytes) -> bytes:
        return self._current().correct_poses(pb.CorrectPosesRequest.FromString(message)).SerializeToString()

    # ------------------------------------------------------------------ end

    def close(self) -> Closed:
        closed = self._registry.close(self._current())
        self._session = None
        return closed

    def expire_idle(self) -> list[Closed]:
        closed = self._registry.expire_idle()
        if closed:
            self._session = None
        return closed
