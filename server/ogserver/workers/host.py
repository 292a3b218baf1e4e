"""``WorkerHost``: the ``SessionHost`` of a server whose sessions live in worker processes (``--workers N``).

Each worker is a child process with a ``Registry`` of its own (``worker.py``), so sessions in
different workers map under different interpreter locks. The server keeps the gRPC front, access
control and the session limits (max_sessions and the per-caller quota count every worker's
sessions), places each new session on the worker holding the fewest, and remembers which worker
holds which session; every other call goes to that worker, which answers with the single server's
own code, refusals included. The cores are split between the workers: each maps with
``torch_threads`` (default min(cores, 8)) divided by the number of workers, at least one, as its
torch threads and its Numba kernels' threads.

A worker that dies takes only its own sessions: calls on them answer UNAVAILABLE, they leave
ListSessions and stop counting against the limits, and the next server started with ``--resume``
brings them back from their checkpoints and recordings, as after a crash of a single server. At
start, ``--resume`` spreads the sessions a dead server left open over the workers the same way.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections import Counter
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path

import grpc
from ogapi.v1 import mapping_pb2 as pb

from ogmapping.queries import Rendered
from ogmapping.stats import MapStats
from ogserver.access.tokens import TokenHash
from ogserver.api.validation import RenderSpec
from ogserver.errors import ServiceError
from ogserver.sessions.counters import FrameTotals, SessionCounters
from ogserver.sessions.hosting import Closed, HostedSession, Opened, Upload
from ogserver.sessions.limits import check_room
from ogserver.sessions.registry import check_label, find, requested_config
from ogserver.sessions.resume import resume_each
from ogserver.sessions.stream_events import StreamEvent
from ogserver.settings import Settings
from ogserver.workers.process import Worker
from ogserver.workers.views import WorkerLatest, WorkerLook
from ogserver.workers.worker import OpenedThere

log = logging.getLogger(__name__)


def worker_threads(settings: Settings) -> int:
    """Threads (torch's and Numba's) each worker maps with: the server's share split evenly, at least one."""
    return max(1, settings.threads() // settings.workers)


@dataclass
class Placed:
    worker: Worker
    owner: str
    config: pb.SessionConfig
    recording: Path
    token: TokenHash  # the session's, kept here too: the live views' viewers may present it


class WorkerSession:
    """A session in a worker process: the ``HostedSession`` the servicer and stream use, and the
    ``ViewedSession`` the live views use (``views.py``)."""

    def __init__(self, placed: Placed) -> None:
        self.id = placed.config.session_id
        self.config = placed.config
        self.worker = placed.worker
        self.token = placed.token
        self.latest = WorkerLatest(placed.worker, self.id)
        self.look = WorkerLook(placed.worker, self.id)
        self._recording = placed.recording

    @property
    def recording(self) -> Path:
        return self._recording

    @property
    def streaming(self) -> bool:
        return self.worker.call("streaming", self.id)

    @contextmanager
    def stream(self, sink: queue.SimpleQueue[StreamEvent]) -> Iterator[None]:
        number = self.worker.attach(sink)  # before the claim: no ack may come before its sink is there
        try:
            self.worker.call("claim_stream", self.id, number)
            try:
                yield
            finally:
                with suppress(ServiceError):  # a dead worker holds no stream any more
                    self.worker.call("release_stream", self.id)
        finally:
            self.worker.detach(number)

    def offer(self, message: pb.Frame, max_pixels: int, sink: queue.SimpleQueue[StreamEvent] | None) -> bool:
        """The worker validates and queues the frame; its acks reach the stream's sink as events."""
        return self.worker.call("offer", self.id, message, max_pixels)

    def count_rejected(self) -> None:
        self.worker.call("count_rejected", self.id)

    def render(self, spec: RenderSpec) -> Rendered:
        return self.worker.call("render", self.id, spec)

    def map_stats(self) -> MapStats:
        return self.worker.call("map_stats", self.id)

    def counters(self) -> SessionCounters:
        return self.worker.call("counters", self.id)

    def snapshot(self) -> bytes:
        return self.worker.call("snapshot", self.id)

    def correct_poses(self, message: pb.CorrectPosesRequest) -> pb.CorrectPosesResponse:
        return self.worker.call("correct_poses", self.id, message)


class WorkerHost:
    def __init__(self, settings: Settings, device: str) -> None:
        self.settings = settings
        self.device = device
        self.record_dir = Path(settings.record_dir)
        threads = worker_threads(settings)
        spawned: list[Worker] = []
        try:
            for number in range(settings.workers):
                spawned.append(Worker.spawn(number, settings, threads))
            self.workers = [worker.ready() for worker in spawned]
        except BaseException:
            for worker in spawned:
                worker.process.kill()
            raise
        log.info("worker mode: %d worker processes, %d torch threads each", settings.workers, threads)
        self._placed: dict[str, Placed] = {}
        self._reserved: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._closing = False
        if settings.resume:
            resume_each(self.record_dir, self._resume)

    # ------------------------------------------------------------------ placing

    def _held(self) -> list[Placed]:
        """The sessions of live workers: those the limits count and ListSessions lists."""
        return [placed for placed in self._placed.values() if placed.worker.alive]

    @contextmanager
    def _place(self, owner: str) -> Iterator[Worker]:
        """A place under the limits and the least-loaded live worker, while a session opens there."""
        with self._lock:
            if self._closing:
                raise ServiceError(grpc.StatusCode.UNAVAILABLE, "the server is shutting down")
            held = self._held()
            check_room(len(held) + self._reserved.total(), self._reserved[owner] + sum(
                placed.owner == owner for placed in held), owner, self.settings.limits.max_sessions,
                self.settings.access.max_sessions_per_client, "server")
            alive = [worker for worker in self.workers if worker.alive]
            if not alive:
                raise ServiceError(grpc.StatusCode.UNAVAILABLE,
                                   "every worker process of the server has stopped; restart the server")
            worker = min(alive, key=lambda candidate: candidate.load)
            worker.load += 1
            self._reserved[owner] += 1
        placed = False
        try:
            yield worker
            placed = True
        finally:
            with self._lock:
                self._reserved[owner] -= 1
                if not placed:
                    worker.load -= 1

    def _register(self, worker: Worker, owner: str, opened: OpenedThere) -> Placed:
        config, recording, token = opened
        placed = Placed(worker, owner, config, recording, token)
        with self._lock:
            self._placed[config.session_id] = placed
        log.info("session %s placed on worker %d (pid %d)", config.session_id, worker.number, worker.pid)
        return placed

    def _resume(self, recording: Path) -> str:
        with self._place("") as worker:
            owner, opened = worker.call("resume", recording)
        return self._register(worker, owner, opened).config.session_id

    def check_label(self, label: str) -> None:
        check_label(label, self.settings)

    def create(self, request: pb.CreateSessionRequest, owner: str) -> Opened:
        requested_config(request, self.settings)  # refused here as a single server refuses, before a place is held
        with self._place(owner) as worker:
            opened, token = worker.call("create", request, owner)
            return Opened(WorkerSession(self._register(worker, owner, opened)), token)

    def restore(self, owner: str, receive: Callable[[], Upload]) -> Opened:
        """The place is held before ``receive`` reads the snapshot: a full server refuses at once."""
        with self._place(owner) as worker:
            opened, token = worker.call("restore", owner, receive())
            return Opened(WorkerSession(self._register(worker, owner, opened)), token)

    # ------------------------------------------------------------------ finding

    def get(self, session_id: str, token: str, field: str = "session_id") -> HostedSession:
        placed = find(self._placed, self._lock, session_id, field)
        placed.worker.call("authorize", placed.config.session_id, token, field)
        return WorkerSession(placed)

    def touch(self, session: HostedSession) -> None:
        assert isinstance(session, WorkerSession)
        with suppress(ServiceError):  # closed meanwhile, or its worker died: nothing left to keep alive
            session.worker.call("touch", session.id)

    def sessions(self, owner: str | None = None) -> list[HostedSession]:
        with self._lock:
            held = self._held()
        return [WorkerSession(placed) for placed in held if owner is None or placed.owner == owner]

    def frame_totals(self) -> FrameTotals:
        """Frames over every session the workers have held; a dead worker's as it last reported them."""
        totals = FrameTotals()
        for worker in self.workers:
            if worker.alive:
                with suppress(ServiceError):
                    worker.totals = worker.call("frame_totals")
            totals += worker.totals
        return totals

    # ------------------------------------------------------------------ closing

    def _forget(self, closed: list[Closed]) -> list[Closed]:
        with self._lock:
            for item in closed:
                placed = self._placed.pop(item.stats.session_id, None)
                if placed is not None:
                    placed.worker.load -= 1
        return closed

    def close(self, session: HostedSession) -> Closed:
        assert isinstance(session, WorkerSession)
        return self._forget([session.worker.call("close", session.id)])[0]

    def expire_idle(self) -> list[Closed]:
        expired: list[Closed] = []
        for worker in self.workers:
            with suppress(ServiceError):
                expired += self._forget(worker.call("expire_idle"))
        return expired

    def close_all(self, timeout: float) -> list[Closed]:
        """Shutdown: every worker closes its sessions at once (the same deadline for all), then exits."""
        with self._lock:
            self._closing = True

        def close(worker: Worker) -> list[Closed]:
            try:
                return worker.call("close_all", timeout) if worker.alive else []
            except ServiceError:
                return []
            finally:
                worker.stop()

        with ThreadPoolExecutor(max_workers=len(self.workers)) as pool:
            return self._forget([item for closed in pool.map(close, self.workers) for item in closed])
