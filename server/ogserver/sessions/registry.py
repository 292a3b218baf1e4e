"""All live sessions: creation within the limits, lookup with token check, idle expiry and closing.

Each session has an owner (the caller identity that created it, see ``access/callers.py``) and the time it
was last used; both live here, beside the session, so the per-caller quota, ListSessions and idle
expiry need nothing from the session itself. Every session writes a checkpoint when it opens (its
identity, the map it starts from) and drops it when it closes cleanly; ``resume`` brings back a
session whose server died, from its checkpoint and its recording (``recording/checkpoint.py``, ``resume.py``).
"""

from __future__ import annotations

import json
import logging
import threading
import time
import uuid
from collections import Counter
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import grpc
from ogapi import recording as layout
from ogapi.v1 import mapping_pb2 as pb

from ogmapping.config import PRESETS, MapperConfig, resolve
from ogmapping.config.resolution import ResolutionConfig
from ogmapping.mapper import Mapper
from ogserver import __version__
from ogserver.access import tokens
from ogserver.api import messages, validation
from ogserver.errors import ServiceError, invalid
from ogserver.recording import checkpoint
from ogserver.recording.checkpoint import CheckpointError, Checkpoints, Identity, Position
from ogserver.recording.disk import StorageError, storage_error
from ogserver.recording.recorder import Recorder
from ogserver.recording.shared_store import RecordingParts, SharedStore
from ogserver.sessions.backlog import read_after
from ogserver.sessions.counters import FrameTotals
from ogserver.sessions.hosting import Closed, Opened, Upload
from ogserver.sessions.ledger import TENSOR as LEDGER_TENSOR
from ogserver.sessions.ledger import FrameLedger
from ogserver.sessions.limits import check_room
from ogserver.sessions.session import Session
from ogserver.settings import Settings

log = logging.getLogger(__name__)
DEFAULT_PRESET = "sparse"  # as ogmap run
Held = TypeVar("Held")


def new_session_id() -> str:
    return uuid.uuid4().hex


def check_label(label: str, settings: Settings) -> None:
    limit = settings.access.max_label_chars
    if len(label) > limit:
        raise invalid("label", f"longer than the server's limit of {limit} characters ({len(label)})")


def requested_config(request: pb.CreateSessionRequest, settings: Settings) -> tuple[str, dict[str, str], MapperConfig]:
    """The preset, overrides and resolved config a CreateSession asks for, or INVALID_ARGUMENT naming why not."""
    check_label(request.label, settings)
    preset = request.preset or DEFAULT_PRESET
    if preset not in PRESETS:
        raise invalid("preset", f"unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
    overrides = dict(request.overrides)
    try:
        config = resolve(preset, overrides=overrides, bounds=settings.config_bounds)
    except ValueError as error:
        raise invalid("overrides", error) from None
    # The image size the step multiple counts from is the operator's: a client's small one would scale
    # every frame's steps and Gaussians far past what its size asks for. A replay pins the server's value.
    server = settings.resolution_reference_pixels
    if config.resolution.reference_pixels not in (server, ResolutionConfig().reference_pixels):
        raise invalid("overrides", f"resolution.reference_pixels is this server's setting "
                                   f"(resolution_reference_pixels: {server}), not a session's")
    config.resolution.reference_pixels = server
    overrides["resolution.reference_pixels"] = str(server)
    return preset, overrides, config


def find(held: Mapping[str, Held], lock: threading.Lock, session_id: str, field: str) -> Held:
    """``held``'s entry for ``session_id`` once its form is checked (refusals name ``field``), or NOT_FOUND."""
    session_id = validation.session_id(session_id, field)
    with lock:
        found = held.get(session_id)
    if found is None:
        raise ServiceError(grpc.StatusCode.NOT_FOUND, f"{field}: no session {session_id}")
    return found


@dataclass
class Tenancy:
    owner: str
    last_used: float  # time.monotonic() of the last call naming the session


class Registry:
    def __init__(self, settings: Settings, device: str) -> None:
        self.settings = settings
        self.device = device
        self.record_dir = Path(settings.record_dir)
        # Cluster mode's shared storage at a URL; the record dir is then this node's scratch space.
        self.store = SharedStore(settings.shared_storage) if settings.shared_storage else None
        self._sessions: dict[str, Session] = {}
        self._tenancy: dict[str, Tenancy] = {}
        # Being closed: no longer served, still counted under max_sessions and the owner's quota (a close
        # that is slow or fails must not free a place early); back to _sessions if its recording fails.
        self._retiring: dict[str, Session] = {}
        self._closed_totals = FrameTotals()
        self._reserved: Counter[str] = Counter()
        self._lock = threading.Lock()
        self._closing = False
        self._before_close: list[Callable[[Session], None]] = []

    def before_close(self, callback: Callable[[Session], None]) -> None:
        """Call ``callback`` with each session once its worker has stopped, before its recording is closed."""
        self._before_close.append(callback)

    @contextmanager
    def _reserve(self, owner: str) -> Iterator[None]:
        """Hold a place under max_sessions and the owner's quota while a map is being built."""
        limit = self.settings.limits.max_sessions
        quota = self.settings.access.max_sessions_per_client
        with self._lock:
            if self._closing:
                raise ServiceError(grpc.StatusCode.UNAVAILABLE, "the server is shutting down")
            held = self._reserved[owner] + sum(tenancy.owner == owner for tenancy in self._tenancy.values())
            check_room(len(self._sessions) + len(self._retiring) + self._reserved.total(), held, owner, limit, quota,
                       "server")
            self._reserved[owner] += 1
        try:
            yield
        finally:
            with self._lock:
                self._reserved[owner] -= 1

    def check_label(self, label: str) -> None:
        check_label(label, self.settings)

    def create(self, request: pb.CreateSessionRequest, owner: str, session_id: str = "") -> Opened:
        """A new session; ``session_id`` is chosen here unless given (cluster mode names the actor first)."""
        preset, overrides, config = requested_config(request, self.settings)
        with self._reserve(owner):
            try:
                mapper = Mapper(config, device=self.device, bounds=self.settings.config_bounds)
            except ValueError as error:  # what this server's device cannot run (render.antialiased off CUDA)
                raise invalid("overrides", error) from None
            return self._open(mapper, preset, overrides, request.label, "", owner, request.realtime, session_id)

    def restore(self, owner: str, receive: Callable[[], Upload], session_id: str = "") -> Opened:
        """Reserve the session's place before ``receive`` reads the snapshot: a full server refuses at once."""
        with self._reserve(owner):
            upload = receive()
            try:
                mapper = Mapper.restore(upload.data, device=self.device, bounds=self.settings.config_bounds)
            except ValueError as error:
                raise invalid("data", f"not a usable snapshot: {error}") from None
            return self._open(mapper, "", {}, upload.label, upload.sha256, owner, session_id=session_id)

    def _open(
        self, mapper: Mapper, preset: str, overrides: dict[str, str], label: str, restored: str, owner: str,
        realtime: bool = False, session_id: str = "",
    ) -> Opened:
        session_id = session_id or new_session_id()
        config = pb.SessionConfig(
            session_id=session_id, preset=preset, overrides=overrides,
            config_json=json.dumps(mapper.config.to_dict()), device=str(mapper.device), label=label,
            created_unix=time.time(), server_version=__version__, restored_from_sha256=restored, realtime=realtime,
        )
        token = tokens.new_token()
        identity = Identity(owner, tokens.TokenHash.of(token), config)
        recorder = Recorder(self.record_dir / f"{session_id}.mcap", config, self._parts(f"{session_id}.mcap"))
        checkpoints = Checkpoints(recorder.path, identity, self.settings.checkpoint_interval, self.store)
        try:
            # without it a crash would lose who the session is
            checkpoints.write(mapper.state(training_state=True), Position())
        except OSError as error:
            recorder.close()
            recorder.path.unlink(missing_ok=True)
            log.error("session %s: cannot write its first checkpoint: %s", session_id, error)
            raise storage_error(error, "a new session's checkpoint") from None
        session = Session(config, identity.token, mapper, recorder, self.settings.limits, self.settings.frame_seconds,
                          checkpoints)
        self._register(session, owner)
        log.info("session %s opened for %s (preset %r, device %s%s)", session_id, owner, preset or "restored",
                 mapper.device, ", realtime" if realtime else "")
        return Opened(session, token)

    def _parts(self, name: str) -> RecordingParts | None:
        return self.store.recording(name) if self.store is not None else None

    def _register(self, session: Session, owner: str) -> None:
        with self._lock:
            self._sessions[session.id] = session
            self._tenancy[session.id] = Tenancy(owner, time.monotonic())

    def resume(self, recording: Path) -> Session:
        """The session ``recording`` belongs to, back as it was when its server died: same id, owner
        and token (checked against the stored hash), its map from its last checkpoint, the recorded
        frames after that which the session mapped as a backlog its worker maps first, the recording
        going on. CheckpointError, RecordingError, ServiceError or StorageError say why it cannot be
        resumed (a checkpoint or recording of another session under this one's name included); the files
        are then left as they were, except a recording that was already copied and replaced (it holds the same)."""
        saved = checkpoint.read(checkpoint.path_for(recording), self.settings.config_bounds)
        session_id = saved.identity.session_id
        if session_id != recording.stem:
            raise CheckpointError(f"it belongs to session {session_id}, not to {recording.name}")
        with self._lock:
            if session_id in self._sessions or session_id in self._retiring:
                raise ServiceError(grpc.StatusCode.ALREADY_EXISTS, f"session {session_id} is already open")
        after = read_after(recording, saved.position.sequence)
        if after.session_id != session_id:
            raise layout.RecordingError(f"{recording.name} is the recording of session {after.session_id or '?'}, "
                                        f"not of {session_id}")
        if after.frames < saved.position.sequence:
            raise CheckpointError(f"it is at frame {saved.position.sequence}, beyond the {after.frames} frames of "
                                  f"{recording.name}")
        backlog = after.backlog()
        with self._reserve(saved.identity.owner):
            try:
                ledger = FrameLedger.from_tensor(saved.state.tensors.pop(LEDGER_TENSOR, None))
                mapper = Mapper.from_state(saved.state, device=self.device, training_state=True,
                                           bounds=self.settings.config_bounds)
            except ValueError as error:
                raise CheckpointError(f"its map cannot be rebuilt: {error}") from None
            recorder = Recorder.resume(recording, self._parts(recording.name))
            checkpoints = Checkpoints(recording, saved.identity, self.settings.checkpoint_interval, self.store,
                                      saved.position.sequence)
            config = pb.SessionConfig()
            config.CopyFrom(saved.identity.config)
            config.device = str(mapper.device)  # this server's, which may not be the crashed one's
            session = Session(config, saved.identity.token, mapper, recorder, self.settings.limits,
                              self.settings.frame_seconds, checkpoints, saved.position, backlog, after.last, ledger)
            self._register(session, saved.identity.owner)
        log.info("session %s resumed for %s from its checkpoint at frame %d, %d recorded frames after it to map "
                 "again (%d skipped as before)", session_id, saved.identity.owner, saved.position.sequence,
                 len(backlog) - len(after.corrections_after),
                 len(after.frames_after) - len(backlog) + len(after.corrections_after))
        return session

    def get(self, session_id: str, token: str, field: str = "session_id") -> Session:
        """The session, after checking the id's form (refusals name ``field``) and the token."""
        session = find(self._sessions, self._lock, session_id, field)
        tokens.check_token(token, session.token)
        self.touch(session)
        return session

    def owner(self, session: Session) -> str:
        """The caller that created the session (worker mode's front-end counts its quota)."""
        with self._lock:
            return self._tenancy[session.id].owner

    def touch(self, session: Session) -> None:
        """The session is in use now: idle expiry counts from here."""
        with self._lock:
            if session.id in self._tenancy:
                self._tenancy[session.id].last_used = time.monotonic()

    def sessions(self, owner: str | None = None) -> list[Session]:
        """Every open session, or those ``owner`` created."""
        with self._lock:
            return [session for session_id, session in self._sessions.items()
                    if owner is None or self._tenancy[session_id].owner == owner]

    def frame_totals(self) -> FrameTotals:
        """Frames over every session this server has held: open, closing and closed."""
        with self._lock:
            live = [*self._sessions.values(), *self._retiring.values()]
            totals = self._closed_totals
        for session in live:
            totals += FrameTotals.of(session.counters())
        return totals

    def _take(self, session_id: str) -> Session | None:
        """Out of the open sessions, into the retiring ones until ``_finish``; call with the lock held."""
        session = self._sessions.pop(session_id, None)
        if session is not None:
            self._retiring[session_id] = session
        return session

    def close(self, session: Session) -> Closed:
        """Finish the session and forget it; if its recording or final snapshot cannot be written
        (StorageError), it stays open, so the client can fetch its map or close it again later."""
        with self._lock:
            if self._take(session.id) is None:
                raise ServiceError(grpc.StatusCode.NOT_FOUND, f"session_id: session {session.id} is already closed")
        try:
            return self._finish(session, self.settings.stop_timeout_seconds)
        except StorageError as error:
            with self._lock:
                self._sessions[session.id] = self._retiring.pop(session.id)
            raise StorageError(error.code, f"{error.message}; the session is still open, close it again later") \
                from None

    def expire_idle(self) -> list[Closed]:
        """Close, as CloseSession would, every session unused for ``session_idle_seconds``.

        A session with an open frame stream or frames still queued is in use.
        """
        limit = self.settings.access.session_idle_seconds
        if not limit:
            return []
        with self._lock:
            now = time.monotonic()
            idle = [session for session_id, session in self._sessions.items()
                    if now - self._tenancy[session_id].last_used >= limit
                    and not session.streaming and not session.counters().pending]
            for session in idle:
                self._take(session.id)
        for session in idle:
            log.info("session %s expired after %g s without use", session.id, limit)
        return self._finish_each(idle, time.monotonic() + self.settings.stop_timeout_seconds)

    def _finish(self, session: Session, timeout: float) -> Closed:
        stopped = session.close(timeout)
        for callback in self._before_close:
            callback(session)
        stats = messages.stats(session.config, session.map_stats(), session.counters())
        snapshot = None
        if self.settings.final_snapshots:
            snapshot = self.record_dir / f"{session.id}.safetensors"
            try:
                data = session.snapshot()
                snapshot.write_bytes(data)
                if self.store is not None:
                    self.store.put(snapshot.name, data)
            except OSError as error:
                snapshot.unlink(missing_ok=True)
                log.error("session %s: cannot write its final snapshot %s: %s", session.id, snapshot, error)
                raise storage_error(error, "the session's final snapshot") from None
        session.recorder.close(stats)
        if session.checkpoints is not None:  # a closed session writes no more of them
            session.checkpoints.remove()
        with self._lock:
            self._retiring.pop(session.id, None)
            self._tenancy.pop(session.id, None)
            self._closed_totals += FrameTotals.of(session.counters())
        checkpoints = session.checkpoints
        log.info("session %s closed after %d frames (%d checkpoints written, %.2f s in all)", session.id, stats.frames,
                 checkpoints.written if checkpoints else 0, checkpoints.seconds if checkpoints else 0.0)
        return Closed(stats, session.recorder.path, snapshot, stopped)

    def close_all(self, timeout: float) -> list[Closed]:
        """Shutdown: refuse new sessions, then close every open one (recording, final snapshot),
        waiting for frames being mapped until ``timeout`` seconds from now, all sessions together."""
        deadline = time.monotonic() + timeout
        with self._lock:
            self._closing = True
            sessions = [session for session_id in list(self._sessions) if (session := self._take(session_id))]
        return self._finish_each(sessions, deadline)

    def _finish_each(self, sessions: list[Session], deadline: float) -> list[Closed]:
        closed = []
        for session in sessions:
            try:
                closed.append(self._finish(session, max(0.0, deadline - time.monotonic())))
            except Exception:  # one broken session must not keep the others' recordings open
                log.exception("session %s: closing failed", session.id)
        return closed
