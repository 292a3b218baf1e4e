"""Which maps a web caller may see: the same rules as the gRPC port.

A caller presents an API key (``key``), a session token (``token``), a client certificate (mutual
TLS), or nothing on an open server. A key or a certificate names a caller, who sees the sessions it
created or restored, as ListSessions shows them; a session token shows that one session, as every
gRPC call that names a session allows; an open server's anonymous caller sees every session. Wrong
credentials count against the address like the gRPC port's (``FailedAuthentications``).
"""

from __future__ import annotations

import hmac
import threading
from dataclasses import dataclass, field
from typing import Protocol
from urllib.parse import urlencode

import grpc
import numpy as np

from ogserver.access.callers import Callers
from ogserver.access.failed_auth import FailedAuthentications
from ogserver.errors import ServiceError
from ogserver.live.views import MappedFrame
from ogserver.sessions.registry import Registry
from ogserver.sessions.session import Session
from ogserver.web.maps import Busy, MapView, keyframe_path


@dataclass(frozen=True)
class Credential:
    key: str = ""
    token: str = ""
    certificate_names: list[bytes] = field(default_factory=list)
    address: str = ""  # the client's, for counting failures

    def query(self) -> str:
        """The credential as the page's links carry it ("" for none, else "?key=..." or "?token=...")."""
        pairs = {"key": self.key} if self.key else {"token": self.token} if self.token else {}
        return f"?{urlencode(pairs)}" if pairs else ""


class Catalogue(Protocol):
    busy: Busy  # what its maps' decodes and renders took

    def visible(self, credential: Credential) -> list[MapView]:
        """The maps the caller may see; ServiceError UNAUTHENTICATED for a wrong credential."""
        ...

    def find(self, map_id: str, credential: Credential) -> MapView | None:
        """One map the caller may see, None where it does not exist or the caller may not see it."""
        ...

    @property
    def asks_credential(self) -> bool:
        """Whether a caller without any credential sees nothing (the page then asks for one)."""
        ...


class SessionSource:
    """A session as a ``maps.Source``."""

    def __init__(self, session: Session) -> None:
        self.session = session
        self.id = session.id
        self.label = session.config.label
        self.mapper = session.mapper

    def latest(self) -> MappedFrame | None:
        """The keyframe whose render the recording's views made last (no render of the web view's own), else
        the newest keyframe (where views are not recorded)."""
        rendered = self.session.latest.rendered
        return rendered[0] if rendered is not None else self.session.latest.keyframe

    def render_of(self, frame: MappedFrame) -> bytes | None:
        rendered = self.session.latest.rendered
        return rendered[1] if rendered is not None and rendered[0] is frame else None

    def version(self) -> int:
        return self.session.latest.keyframes

    def keyframe_path(self) -> np.ndarray:
        return keyframe_path(self.mapper)

    def counters(self) -> dict[str, float]:
        counters = self.session.counters()
        return {"received": counters.received, "mapped": counters.mapped, "skipped": counters.skipped,
                "processing_fps": round(counters.processing_fps, 2)}


class Sessions:
    """The server's open sessions, each with its ``MapView`` while it is open."""

    def __init__(self, registry: Registry, callers: Callers, failures: FailedAuthentications,
                 min_seconds: float) -> None:
        self.registry = registry
        self.callers = callers
        self.failures = failures
        self.min_seconds = min_seconds
        self.busy = Busy()
        self._lock = threading.Lock()
        self._views: dict[str, MapView] = {}

    @property
    def asks_credential(self) -> bool:
        return not self.callers.open

    def _view(self, session: Session) -> MapView:
        """The session's view, made on first sight; closed sessions' views are dropped then."""
        with self._lock:
            view = self._views.get(session.id)
            if view is None:
                open_ids = {item.id for item in self.registry.sessions()}
                self._views = {key: value for key, value in self._views.items() if key in open_ids}
                view = self._views[session.id] = MapView(SessionSource(session), self.min_seconds, self.busy)
            return view

    def _sessions(self, credential: Credential) -> list[Session]:
        with self.failures.guard(credential.address):
            if credential.token:
                return self._held(credential.token)
            try:
                owner = self.callers.identify(credential.key, credential.certificate_names or None)
            except ServiceError:
                if not credential.key:
                    raise
                return self._held(credential.key)  # a session token, typed into the page's one field
        return self.registry.sessions(owner)

    def _held(self, token: str) -> list[Session]:
        """The session whose token this is."""
        held = [session for session in self.registry.sessions() if session.token.matches(token)]
        if not held:
            raise ServiceError(grpc.StatusCode.UNAUTHENTICATED, "not an API key or session token this server accepts")
        return held

    def visible(self, credential: Credential) -> list[MapView]:
        return [self._view(session) for session in self._sessions(credential)]

    def find(self, map_id: str, credential: Credential) -> MapView | None:
        return next((self._view(s) for s in self._sessions(credential) if s.id == map_id), None)


class OneMap:
    """A single map (``ogserver view``, which ``ogclient view`` starts), seen by whoever holds its one token."""

    asks_credential = True

    def __init__(self, view: MapView, token: str) -> None:
        self.view = view
        self.token = token
        self.busy = view.busy

    def visible(self, credential: Credential) -> list[MapView]:
        offered = credential.token or credential.key  # the login form's one field sends it as key
        if not hmac.compare_digest(offered.encode(), self.token.encode()):
            raise ServiceError(grpc.StatusCode.UNAUTHENTICATED, "token: missing or wrong (it is in the URL printed)")
        return [self.view]

    def find(self, map_id: str, credential: Credential) -> MapView | None:
        return next((view for view in self.visible(credential) if view.source.id == map_id), None)
