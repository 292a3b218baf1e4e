"""Session checkpoints: a session's map and what resuming it after a crash needs, in one file.

``<session>.checkpoint.safetensors`` lies next to the session's recording. It is a snapshot
(``ogmapping.persist.snapshot``: the map's tensors, its config) in float32 and with the map's training state
(``ogmapping.persist.training``: keyframes, Adam's moments, random states), so the resumed session maps the
frames after it as the uninterrupted one would have. Its safetensors metadata also holds, as
JSON, the session's identity (id, owner, the recorded ``SessionConfig`` with label and resolved
config, a salted hash of its token, never the token) and the position of the map in the recording:
the sequence of the last frame it holds (the n-th recorded frame has sequence n) and that frame's
``index``. A sha256 of the whole header (the metadata and the tensors' layout) and the tensor bytes, in
the same metadata, lets a resume refuse a damaged or edited file: an owner changed by hand, a checkpoint
of version 1 (whose identity no digest covered). It detects mistakes, not a forger who can write the
record dir and compute a sha256.
A checkpoint replaces the previous one atomically (temporary file, fsync, rename, fsync of the
directory): the file under its name is always a whole checkpoint, the old one or the new one.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from google.protobuf import json_format
from ogapi.v1 import mapping_pb2 as pb

from ogmapping.config import ConfigBounds
from ogmapping.persist import snapshot
from ogmapping.persist.state import MapState
from ogserver.access.tokens import TokenHash

log = logging.getLogger(__name__)
FORMAT = "ogserver-checkpoint"
VERSION = 2  # 1: the digest covered the tensor bytes only
SUFFIX = ".checkpoint.safetensors"
KEY = "checkpoint"  # the safetensors metadata entry with the JSON below
DIGEST_KEY = "checkpoint_sha256"


class CheckpointError(ValueError):
    """A checkpoint that cannot be trusted: damaged, cut, of another format or session."""


def path_for(recording: Path) -> Path:
    """``<session>.checkpoint.safetensors`` beside ``<session>.mcap``."""
    return recording.with_name(recording.stem + SUFFIX)


@dataclass(frozen=True)
class Identity:
    """Who the session is: what a resumed session must keep."""

    owner: str
    token: TokenHash
    config: pb.SessionConfig  # as the recording's first message: id, label, preset, resolved config

    @property
    def session_id(self) -> str:
        return self.config.session_id


@dataclass(frozen=True)
class Position:
    """Where the map stands in the session's frames: it holds the recorded frames 1..``sequence``."""

    sequence: int = 0
    index: int = 0  # Frame.index of frame ``sequence`` (0 before any)


@dataclass(frozen=True)
class Checkpoint:
    identity: Identity
    position: Position
    state: MapState


def encode(identity: Identity, position: Position, state: MapState) -> bytes:
    """The checkpoint file's bytes: the snapshot of ``state`` with the identity, position and payload digest."""
    entry = {
        "format": FORMAT, "version": VERSION, "written_unix": time.time(),
        "session_id": identity.session_id, "owner": identity.owner,
        "token_salt": identity.token.salt, "token_sha256": identity.token.sha256,
        "session_config": json_format.MessageToDict(identity.config),
        "sequence": position.sequence, "index": position.index,
    }
    # float32 throughout: the session maps on from it, so it must hold the map as it was, not rounded
    return _with_metadata(snapshot.encode(state, half=False), {KEY: json.dumps(entry)})


def _split(data: bytes) -> tuple[dict, bytes]:
    """A safetensors file's header (parsed) and its tensor bytes; the caller has checked the header length."""
    length = int.from_bytes(data[:8], "little")
    return json.loads(data[8 : 8 + length]), data[8 + length :]


def _digest(header: dict, payload: bytes) -> str:
    """sha256 of the header without the digest itself (canonical JSON) and of the tensor bytes."""
    metadata = {key: value for key, value in header.get("__metadata__", {}).items() if key != DIGEST_KEY}
    canonical = json.dumps({**header, "__metadata__": metadata}, sort_keys=True, separators=(",", ":"))
    digest = hashlib.sha256(canonical.encode())
    digest.update(payload)
    return digest.hexdigest()


def _with_metadata(data: bytes, extra: dict[str, str]) -> bytes:
    """``data`` (safetensors) with ``extra`` and the digest of the whole added to its metadata. Tensor
    offsets count from the payload's start, so only the header changes (padded to 8 bytes, as
    safetensors writes it)."""
    header, payload = _split(data)
    header["__metadata__"] = {**header.get("__metadata__", {}), **extra}
    header["__metadata__"][DIGEST_KEY] = _digest(header, payload)
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)
    return len(text).to_bytes(8, "little") + text + payload


def decode(data: bytes, bounds: ConfigBounds | None = None) -> Checkpoint:
    """The checkpoint in ``data``; ``CheckpointError`` naming what is wrong with anything else."""
    try:
        metadata = snapshot.read_metadata(data)
    except ValueError as error:
        raise CheckpointError(f"not a checkpoint: {error}") from None
    if KEY not in metadata:
        raise CheckpointError("not a checkpoint: a snapshot without the checkpoint's metadata")
    try:
        entry = json.loads(metadata[KEY])
        version = entry.get("version")
        if entry.get("format") != FORMAT or version not in (1, VERSION):
            raise CheckpointError(f"format {entry.get('format')!r} version {version!r} is not "
                                  f"{FORMAT!r} version {VERSION}")
        if version == 1:  # deliberately refused: its owner and token hash could be edited unnoticed
            raise CheckpointError("version 1, from an older server: no digest covers its owner and session; "
                                  "`ogclient replay` maps its recording into a new session")
        if _digest(*_split(data)) != metadata.get(DIGEST_KEY):
            raise CheckpointError(f"damaged or edited: its metadata and tensor bytes do not match {DIGEST_KEY}")
        config = json_format.ParseDict(entry["session_config"], pb.SessionConfig())
        identity = Identity(str(entry["owner"]), TokenHash(str(entry["token_salt"]), str(entry["token_sha256"])),
                            config)
        position = Position(int(entry["sequence"]), int(entry["index"]))
    except CheckpointError:
        raise
    except (AttributeError, KeyError, TypeError, ValueError, json_format.ParseError) as error:
        raise CheckpointError(f"malformed metadata: {type(error).__name__}: {error}") from None
    if identity.session_id != entry["session_id"] or position.sequence < 0:
        raise CheckpointError("malformed metadata: inconsistent session id or sequence")
    try:
        state = snapshot.decode(data, bounds)
    except ValueError as error:
        raise CheckpointError(f"its map: {error}") from None
    return Checkpoint(identity, position, state)


def read(path: Path, bounds: ConfigBounds | None = None) -> Checkpoint:
    try:
        data = path.read_bytes()
    except OSError as error:
        raise CheckpointError(f"cannot read {path.name}: {error.strerror or error}") from None
    return decode(data, bounds)


def write_atomically(path: Path, data: bytes) -> None:
    """``path`` holds ``data`` or, if this fails or the process dies, what it held before."""
    temporary = path.with_name(path.name + ".tmp")
    try:
        with open(temporary, "wb") as file:
            file.write(data)
            file.flush()
            os.fsync(file.fileno())
        os.replace(temporary, path)
    except OSError:
        temporary.unlink(missing_ok=True)
        raise
    directory = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(directory)  # the rename itself survives a power cut
    finally:
        os.close(directory)


class SharedStore(Protocol):
    """Where else checkpoints go (``shared_store.SharedStore``: an fsspec store)."""

    def put(self, name: str, data: bytes) -> None: ...

    def remove(self, name: str) -> None: ...


class Checkpoints:
    """One session's checkpoints: where they go (and, with shared storage, where else), what each carries
    besides the map, when one is due."""

    def __init__(self, recording: Path, identity: Identity, interval: int, store: SharedStore | None = None,
                 last: int = 0) -> None:
        self.path = path_for(recording)
        self.store = store
        self.identity = identity
        self.interval = interval  # frames; 0: only the one written when the session opens
        self.last = last  # the sequence of the last checkpoint written (or tried)
        self.written = 0
        self.seconds = 0.0  # spent writing them, encoding included

    def due(self, sequence: int) -> bool:
        """``interval`` recorded frames after the last one: a realtime session's mapped frames fall on
        any sequence, its skipped frames in between."""
        return self.interval > 0 and sequence >= self.last + self.interval

    def write(self, state: MapState, position: Position) -> None:
        """Raises OSError if it could not be written; the previous checkpoint then still stands, and the
        next one is due ``interval`` frames later (a full disk is not tried at every frame)."""
        self.last = position.sequence
        start = time.perf_counter()
        data = encode(self.identity, position, state)
        write_atomically(self.path, data)
        if self.store is not None:  # after the recording's parts up to this frame, which were uploaded first
            self.store.put(self.path.name, data)
        elapsed = time.perf_counter() - start
        self.written += 1
        self.seconds += elapsed
        log.debug("session %s: checkpoint at sequence %d in %.3f s", self.identity.session_id, position.sequence,
                  elapsed)

    def write_if_due(self, position: Position, capture: Callable[[], MapState]) -> None:
        """A checkpoint at ``position`` of the map ``capture`` takes, when one is due. A failed write is logged
        and the previous checkpoint stands (a resume replays more frames); so does any other failure, logged
        with its traceback instead of ending the session's worker thread, which would leave every later frame
        of the session waiting for ever."""
        if not self.due(position.sequence):
            return
        session = self.identity.session_id
        try:
            self.write(capture(), position)
        except OSError as error:
            log.error("session %s: cannot write its checkpoint at sequence %d: %s", session, position.sequence,
                      error.strerror or error)
        except Exception:  # a defect in capturing the state must not stop the session's mapping
            log.exception("session %s: cannot capture its checkpoint at sequence %d", session, position.sequence)

    def remove(self) -> None:
        """The session closed cleanly: nothing to resume."""
        self.path.unlink(missing_ok=True)
        if self.store is not None:
            try:
                self.store.remove(self.path.name)
            except OSError as error:  # the recording is closed and published: only a stale checkpoint is left
                log.error("session %s: cannot remove its checkpoint from the shared storage: %s",
                          self.identity.session_id, error)
