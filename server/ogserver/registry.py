"""All live sessions: creation within the limits, lookup with token check, and closing."""

from __future__ import annotations

import json
import logging
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import grpc
from ogapi.v1 import mapping_pb2 as pb

from ogmapping.config import PRESETS, resolve
from ogmapping.mapper import Mapper
from ogserver import __version__, auth, messages, validation
from ogserver.errors import ServiceError, invalid
from ogserver.recorder import Recorder
from ogserver.session import Session
from ogserver.settings import Settings

log = logging.getLogger(__name__)
DEFAULT_PRESET = "sparse"  # as ogmap run


@dataclass(frozen=True)
class Closed:
    stats: pb.Stats
    recording: Path
    snapshot: Path | None


class Registry:
    def __init__(self, settings: Settings, device: str) -> None:
        self.settings = settings
        self.device = device
        self.record_dir = Path(settings.record_dir)
        self._sessions: dict[str, Session] = {}
        self._reserved = 0
        self._lock = threading.Lock()
        self._closing = False

    @contextmanager
    def _slot(self) -> Iterator[None]:
        """Hold a place under max_sessions while a map is being built."""
        limit = self.settings.limits.max_sessions
        with self._lock:
            if self._closing:
                raise ServiceError(grpc.StatusCode.UNAVAILABLE, "the server is shutting down")
            if len(self._sessions) + self._reserved >= limit:
                raise ServiceError(grpc.StatusCode.RESOURCE_EXHAUSTED,
                                   f"the server already holds its limit of {limit} sessions")
            self._reserved += 1
        try:
            yield
        finally:
            with self._lock:
                self._reserved -= 1

    def create(self, request: pb.CreateSessionRequest) -> Session:
        preset = request.preset or DEFAULT_PRESET
        if preset not in PRESETS:
            raise invalid("preset", f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
        overrides = dict(request.overrides)
        try:
            config = resolve(preset, overrides=overrides, bounds=self.settings.config_bounds)
        except ValueError as error:
            raise invalid("overrides", error) from None
        with self._slot():
            mapper = Mapper(config, device=self.device)
            return self._open(mapper, preset, overrides, request.label, "")

    def restore(self, data: bytes, label: str, sha256: str) -> Session:
        with self._slot():
            try:
                mapper = Mapper.restore(data, device=self.device, bounds=self.settings.config_bounds)
            except ValueError as error:
                raise invalid("data", f"not a usable snapshot: {error}") from None
            return self._open(mapper, "", {}, label, sha256)

    def _open(self, mapper: Mapper, preset: str, overrides: dict[str, str], label: str, restored: str) -> Session:
        session_id = uuid.uuid4().hex
        config = pb.SessionConfig(
            session_id=session_id, preset=preset, overrides=overrides,
            config_json=json.dumps(mapper.config.to_dict()), device=str(mapper.device), label=label,
            created_unix=time.time(), server_version=__version__, restored_from_sha256=restored,
        )
        recorder = Recorder(self.record_dir / f"{session_id}.mcap", config)
        session = Session(config, auth.new_token(), mapper, recorder, self.settings.limits, self.settings.frame_seconds)
        with self._lock:
            self._sessions[session_id] = session
        log.info("session %s opened (preset %r, device %s)", session_id, preset or "restored", mapper.device)
        return session

    def get(self, session_id: str, token: str, field: str = "session_id") -> Session:
        """The session, after checking the id's form (refusals name ``field``) and the token."""
        session_id = validation.session_id(session_id, field)
        with self._lock:
            session = self._sessions.get(session_id)
        if session is None:
            raise ServiceError(grpc.StatusCode.NOT_FOUND, f"{field}: no session {session_id}")
        auth.check_token(token, session.token)
        return session

    def sessions(self) -> list[Session]:
        with self._lock:
            return list(self._sessions.values())

    def close(self, session: Session) -> Closed:
        with self._lock:
            if self._sessions.pop(session.id, None) is None:
                raise ServiceError(grpc.StatusCode.NOT_FOUND, f"session_id: session {session.id} is already closed")
        return self._finish(session)

    def _finish(self, session: Session) -> Closed:
        session.close()
        stats = messages.stats(session.config, session.map_stats(), session.counters())
        snapshot = None
        if self.settings.final_snapshots:
            snapshot = self.record_dir / f"{session.id}.safetensors"
            snapshot.write_bytes(session.snapshot())
        session.recorder.close(stats)
        log.info("session %s closed after %d frames", session.id, stats.frames)
        return Closed(stats, session.recorder.path, snapshot)

    def close_all(self) -> list[Closed]:
        """Shutdown: refuse new sessions, then close every open one (recording, final snapshot)."""
        with self._lock:
            self._closing = True
            sessions = list(self._sessions.values())
            self._sessions.clear()
        closed = []
        for session in sessions:
            try:
                closed.append(self._finish(session))
            except Exception:  # one broken session must not keep the others' recordings open
                log.exception("session %s: closing failed", session.id)
        return closed
