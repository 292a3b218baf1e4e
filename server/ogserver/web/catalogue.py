"""Which maps a web caller may see: the viewers' rules (``access/viewers.py``), the gRPC port's own.

``Sessions`` shows a server's open sessions by the caller's credential; ``OneMap`` a single map (``ogserver
view``) to whoever holds its one token.
"""

from __future__ import annotations

import hmac
import threading
from typing import Protocol

import grpc
import numpy as np

from ogserver.access.viewers import Credential, Viewers
from ogserver.errors import ServiceError
from ogserver.live.views import Shown
from ogserver.sessions.hosting import ViewedSession
from ogserver.web.maps import Busy, MapView


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
    """A session as a ``maps.Source``, in this process or in a worker process (each answer then a call to it)."""

    def __init__(self, session: ViewedSession) -> None:
        self.session = session
        self.id = session.id
        self.label = session.config.label
        self.look = session.look

    def shown(self) -> Shown:
        return self.session.latest.shown()

    def keyframe_path(self) -> np.ndarray:
        return self.look.keyframe_path()

    def counters(self) -> dict[str, float]:
        counters = self.session.counters()
        return {"received": counters.received, "mapped": counters.mapped, "skipped": counters.skipped,
                "processing_fps": round(counters.processing_fps, 2)}


class Sessions:
    """The server's open sessions, each with its ``MapView`` while it is open."""

    def __init__(self, viewers: Viewers, min_seconds: float) -> None:
        self.viewers = viewers
        self.registry = viewers.registry
        self.min_seconds = min_seconds
        self.busy = Busy()
        self._lock = threading.Lock()
        self._views: dict[str, MapView] = {}

    @property
    def asks_credential(self) -> bool:
        return not self.viewers.callers.open

    def _view(self, session: ViewedSession) -> MapView:
        """The session's view, made on first sight; closed sessions' views are dropped then."""
        with self._lock:
            view = self._views.get(session.id)
            if view is None:
                open_ids = {item.id for item in self.registry.sessions()}
                self._views = {key: value for key, value in self._views.items() if key in open_ids}
                view = self._views[session.id] = MapView(SessionSource(session), self.min_seconds, self.busy)
            return view

    def _sessions(self, credential: Credential) -> list[ViewedSession]:
        return self.viewers.scope(credential).sessions(self.registry)

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
