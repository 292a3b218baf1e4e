"""Where sessions live: the one seam between the servicer and the sessions it serves.

The servicer, the frame stream, metrics and expiry talk to a ``SessionHost`` and the
``HostedSession`` objects it hands out, never to how they are placed. ``Registry`` (sessions in
this process, each a ``Session`` with its own worker thread) is one host; ``workers.host.WorkerHost``
(sessions in worker processes of the server) and ``cluster.host.ClusterHost`` (each session a
``Registry`` of one inside a named Ray actor, reached through a proxy) are the others. The registry
and session logic are written once; only their placement differs. The live views (the web view, the
Foxglove view) need a little more of a session (``ViewedSession``), which the in-process and the
worker hosts give.
"""

from __future__ import annotations

import queue
from collections.abc import Callable
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from ogapi.v1 import mapping_pb2 as pb

from ogmapping.queries import Rendered
from ogmapping.stats import MapStats
from ogserver.access.tokens import TokenHash
from ogserver.api.validation import RenderSpec
from ogserver.live.map_look import MapLook
from ogserver.live.views import Latest
from ogserver.sessions.counters import FrameTotals, SessionCounters
from ogserver.sessions.stream_events import StreamEvent
from ogserver.settings import Settings


@dataclass(frozen=True)
class Closed:
    stats: pb.Stats
    recording: Path
    snapshot: Path | None
    stopped: bool  # the frame being mapped, if any, finished before the recording was closed


@dataclass(frozen=True)
class Upload:
    """A snapshot received by RestoreSession."""

    data: bytes
    label: str
    sha256: str


class HostedSession(Protocol):
    """What the servicer and the frame stream use of one session, wherever it lives."""

    id: str
    config: pb.SessionConfig

    @property
    def recording(self) -> Path: ...

    @property
    def streaming(self) -> bool: ...

    def stream(self, sink: queue.SimpleQueue[StreamEvent]) -> AbstractContextManager[None]: ...

    def offer(self, message: pb.Frame, max_pixels: int, sink: queue.SimpleQueue[StreamEvent] | None) -> bool: ...

    def count_rejected(self) -> None: ...

    def render(self, spec: RenderSpec) -> Rendered: ...

    def map_stats(self) -> MapStats: ...

    def counters(self) -> SessionCounters: ...

    def snapshot(self) -> bytes: ...

    def correct_poses(self, message: pb.CorrectPosesRequest) -> pb.CorrectPosesResponse: ...


class ViewedSession(HostedSession, Protocol):
    """A session as the live views see it: its token (a viewer may present it), the frames it mapped and
    its map's answers."""

    token: TokenHash
    latest: Latest
    look: MapLook


class ViewedHost(Protocol):
    """The sessions the live views look at, the same ones ``SessionHost.sessions`` lists."""

    def sessions(self, owner: str | None = None) -> list[ViewedSession]: ...


@dataclass(frozen=True)
class Opened:
    """A new session and its token: the only time the server has the token, not just its hash."""

    session: HostedSession
    token: str


class SessionHost(Protocol):
    """Creates, finds, lists and closes sessions within the limits, wherever they live."""

    settings: Settings
    device: str
    record_dir: Path

    def check_label(self, label: str) -> None: ...

    def create(self, request: pb.CreateSessionRequest, owner: str) -> Opened: ...

    def restore(self, owner: str, receive: Callable[[], Upload]) -> Opened: ...

    def get(self, session_id: str, token: str, field: str = "session_id") -> HostedSession: ...

    def touch(self, session: HostedSession) -> None: ...

    def sessions(self, owner: str | None = None) -> list[HostedSession]: ...

    def frame_totals(self) -> FrameTotals: ...

    def close(self, session: HostedSession) -> Closed: ...

    def expire_idle(self) -> list[Closed]: ...

    def close_all(self, timeout: float) -> list[Closed]: ...
