"""A worker process (``python -m ogserver.workers.worker FD THREADS``): a ``Registry`` of the sessions the
server placed on it, served over the socket pair end the server handed it as ``FD``.

The server sends the settings first; the worker builds its registry (the single server's code,
unchanged: same sessions, recordings, checkpoints and refusals), warms up, and answers ``ready``.
Then each ``call`` runs in a thread of its own pool (a frame offer waiting on its session's queue,
renders and stats run side by side, as the gRPC threads of a single server would) and is answered
with its ``reply``. A frame stream's acks go back unasked, as ``event`` messages tagged with the
number the server gave the stream. With views on, the worker's own ``LiveView`` (no Foxglove) writes
keyframes' renders and point clouds into its sessions' recordings, as a single server does; the server's
live views (the web view, Foxglove) ask for the rest, a call per answer (``views.py``).

When the server goes away (its end of the socket closes) the worker exits at once without closing
anything, as the server itself would have died: the next server with ``--resume`` brings the
sessions back. SIGINT is ignored: a Ctrl-C in a terminal reaches the whole process group, and the
server closes its workers' sessions itself.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import sys
import threading
from concurrent.futures import ThreadPoolExecutor
from contextlib import ExitStack, suppress
from pathlib import Path
from typing import Any

import ogmapping  # noqa: F401 (before torch: it sets the OpenMP wait policy torch's pool reads at start)

# isort: split
import grpc
import torch
from ogapi.v1 import mapping_pb2 as pb

from ogmapping.config.overrides import assign
from ogmapping.runtime.profile import resolve_device
from ogmapping.warmup import warm_up
from ogserver import LOG_FORMAT
from ogserver.access.tokens import TokenHash
from ogserver.errors import ServiceError
from ogserver.live.publisher import LiveView
from ogserver.live.views import Pending, Shown
from ogserver.sessions.counters import FrameTotals, SessionCounters
from ogserver.sessions.hosting import Closed, Upload
from ogserver.sessions.registry import Registry
from ogserver.sessions.session import Session
from ogserver.sessions.stream_events import Acked, SessionClosed, StreamEvent
from ogserver.settings import LABEL, Settings
from ogserver.workers import codec
from ogserver.workers.views import QUESTIONS, SERVER_READER

log = logging.getLogger(__name__)
OpenedThere = tuple[pb.SessionConfig, Path, TokenHash]  # a session's config, its recording and its token's hash


class Link:
    """The worker's end of its socket pair: one message at a time, from any thread."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self._lock = threading.Lock()

    def send(self, message: list[Any]) -> None:
        with self._lock:
            codec.send(self.sock, message)


class Forward:
    """A stream's event sink inside the worker: what the session puts in it goes to the server."""

    def __init__(self, link: Link, stream: int) -> None:
        self._link = link
        self._stream = stream

    def put(self, event: StreamEvent) -> None:
        if isinstance(event, Acked | SessionClosed):
            self._link.send(["event", self._stream, event])


class WorkerSessions:
    """What the server may call in a worker: the registry's operations, naming sessions by id."""

    CALLS = frozenset({
        "create", "restore", "resume", "authorize", "touch", "claim_stream", "release_stream", "streaming", "offer",
        "count_rejected", "render", "map_stats", "counters", "snapshot", "correct_poses", "close", "expire_idle",
        "close_all", "frame_totals", "take_latest", "shown", "look",
    })

    def __init__(self, registry: Registry, link: Link) -> None:
        self.registry = registry
        self._link = link
        self._streams: dict[str, tuple[ExitStack, Forward]] = {}

    def _session(self, session_id: str) -> Session:
        found = next((session for session in self.registry.sessions() if session.id == session_id), None)
        if found is None:
            raise ServiceError(grpc.StatusCode.NOT_FOUND, f"session_id: no session {session_id}")
        return found

    @staticmethod
    def _described(session: Session) -> OpenedThere:
        return session.config, session.recording, session.token

    def create(self, request: pb.CreateSessionRequest, owner: str) -> tuple[OpenedThere, str]:
        """The new session, and its token."""
        opened = self.registry.create(request, owner)
        return self._described(opened.session), opened.token

    def restore(self, owner: str, upload: Upload) -> tuple[OpenedThere, str]:
        opened = self.registry.restore(owner, lambda: upload)
        return self._described(opened.session), opened.token

    def resume(self, recording: Path) -> tuple[str, OpenedThere]:
        """A session a dead server left open, and its owner."""
        session = self.registry.resume(recording)
        return self.registry.owner(session), self._described(session)

    def authorize(self, session_id: str, token: str, field: str) -> None:
        self.registry.get(session_id, token, field)

    def touch(self, session_id: str) -> None:
        self.registry.touch(self._session(session_id))

    def claim_stream(self, session_id: str, stream: int) -> None:
        session = self._session(session_id)
        held = ExitStack()
        forward = Forward(self._link, stream)
        held.enter_context(session.stream(forward))  # type: ignore[arg-type]  # a sink that forwards
        self._streams[session_id] = (held, forward)

    def release_stream(self, session_id: str) -> None:
        held, _ = self._streams.pop(session_id, (ExitStack(), None))
        held.close()

    def streaming(self, session_id: str) -> bool:
        return self._session(session_id).streaming

    def offer(self, session_id: str, message: pb.Frame, max_pixels: int) -> bool:
        _, forward = self._streams.get(session_id, (None, None))
        return self._session(session_id).offer(message, max_pixels, forward)  # type: ignore[arg-type]

    def count_rejected(self, session_id: str) -> None:
        self._session(session_id).count_rejected()

    def render(self, session_id: str, spec: Any) -> Any:
        return self._session(session_id).render(spec)

    def map_stats(self, session_id: str) -> Any:
        return self._session(session_id).map_stats()

    def counters(self, session_id: str) -> SessionCounters:
        return self._session(session_id).counters()

    def snapshot(self, session_id: str) -> bytes:
        return self._session(session_id).snapshot()

    def correct_poses(self, session_id: str, message: pb.CorrectPosesRequest) -> pb.CorrectPosesResponse:
        return self._session(session_id).correct_poses(message)

    def take_latest(self, session_id: str) -> Pending | None:
        return self._session(session_id).latest.take(SERVER_READER)

    def shown(self, session_id: str) -> Shown:
        return self._session(session_id).latest.shown()

    def look(self, session_id: str, question: str, *args: Any) -> Any:
        """One of the live views' questions of a session's map (``MapLook``), within the server's bounds."""
        if question not in QUESTIONS:
            raise ServiceError(grpc.StatusCode.INTERNAL, f"a map has no question {question!r}")
        settings = self.registry.settings
        if question == "points" and args[0] > settings.live.view_points:
            raise ServiceError(grpc.StatusCode.INVALID_ARGUMENT, f"points: over live.view_points "
                               f"({args[0]} > {settings.live.view_points})")
        if question == "render_jpeg" and args[1].width * args[1].height > settings.limits.max_image_pixels:
            raise ServiceError(grpc.StatusCode.INVALID_ARGUMENT, "render_jpeg: over limits.max_image_pixels")
        return getattr(self._session(session_id).look, question)(*args)

    def close(self, session_id: str) -> Closed:
        return self.registry.close(self._session(session_id))

    def expire_idle(self) -> list[Closed]:
        return self.registry.expire_idle()

    def close_all(self, timeout: float) -> list[Closed]:
        return self.registry.close_all(timeout)

    def frame_totals(self) -> FrameTotals:
        return self.registry.frame_totals()

    def serve(self, call_id: int, method: str, args: list[Any]) -> None:
        """Run one call and send its reply: its value, or the refusal (or failure) it raised."""
        try:
            if method not in self.CALLS:
                raise ServiceError(grpc.StatusCode.INTERNAL, f"a worker has no call {method!r}")
            reply = ["reply", call_id, True, getattr(self, method)(*args)]
        except ServiceError as refusal:
            reply = ["reply", call_id, False, refusal]
        except Exception as error:  # the servicer answers INTERNAL with its text, as for a single server
            log.exception("worker call %s failed", method)
            reply = ["reply", call_id, False, error]
        with suppress(OSError):  # the server is gone; the reader sees it too and ends the process
            self._link.send(reply)


def settings_from(mapping: dict[str, Any]) -> Settings:
    settings = Settings()
    assign(settings, mapping, LABEL)
    settings.validate()
    return settings


def main(argv: list[str]) -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    logging.basicConfig(level=logging.INFO, format=LOG_FORMAT)
    link = Link(socket.socket(fileno=int(argv[0])))
    settings = settings_from(codec.receive(link.sock))
    torch.set_num_threads(int(argv[1]))
    device = str(resolve_device(settings.device))
    if settings.warm_up:
        log.info("worker %d warming up on %s: %.1f s", os.getpid(), device, warm_up(device))
    registry = Registry(settings, device)
    live = settings.live
    views = LiveView(registry, live, None).start() if live.view_seconds and live.record_views else None
    sessions = WorkerSessions(registry, link)
    pool = ThreadPoolExecutor(max_workers=2 * settings.access.max_concurrent_calls + 8, thread_name_prefix="call")
    link.send(["ready", os.getpid()])
    while True:
        try:
            message = codec.receive(link.sock)
        except (EOFError, OSError):  # the server died: leave every session as it was, for --resume
            os._exit(1)
        if message[0] == "stop":
            break
        _, call_id, method, args = message
        pool.submit(sessions.serve, call_id, method, args)
    if views is not None:
        views.stop()
    logging.shutdown()
    link.sock.close()
    os._exit(0)  # calls still waiting (none once the server closed every session) must not hold the exit


if __name__ == "__main__":
    main(sys.argv[1:])
