"""Shared storage at an fsspec URL (s3://, gs://, file://, memory://): a session's recording and checkpoints
kept where every node of a cluster reads them, so a session whose node is lost resumes on another.

Object stores neither append nor seek, and an MCAP recording grows by appends (a chunk and a
provisional end per frame, ``recorder.RecordingFile``). So the recording is written to a local file
as on a single server, and each stretch of bytes a flush commits (one frame's chunk) is uploaded, before
the frame is mapped and acknowledged, as an object of its own: ``<id>.mcap.parts/<generation>-<offset>-
<length>[-end]``. A part is one upload, and its name says where it goes and how long it is, so a part cut
short (a local filesystem mid-write) is recognised and ignored with everything after it. A resumed
session's recording (copied into a new file, ``Recorder.resume``) starts a new generation with its
whole copy as the first part; the older generations are removed once that part is up. Closing uploads
the finished file as ``<id>.mcap`` and removes the parts. Checkpoints and final snapshots are whole
files, uploaded under a temporary name and moved into place. fsspec is imported only when a URL is set
(the ``cluster`` extra): local paths never need it.
"""

from __future__ import annotations

import errno
import logging
import re
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from ogserver.recording import checkpoint
from ogserver.recording.recorder import PROVISIONAL_END

log = logging.getLogger(__name__)
PART = re.compile(r"(\d+)-(\d+)-(\d+)(-end)?")


@contextmanager
def uploading(what: str) -> Iterator[None]:
    """Any failure of the store as an OSError, which the recorder and checkpoints already turn into statuses."""
    try:
        yield
    except OSError:
        raise
    except Exception as error:  # a store's client raises its own kinds (botocore, aiohttp, ...)
        raise OSError(errno.EIO, f"shared storage: {what}: {type(error).__name__}: {error}") from error


@dataclass(frozen=True, order=True)
class Part:
    generation: int
    offset: int
    length: int
    end: bool  # the part that ends the file (a closed recording's summary): no provisional end after it

    @property
    def name(self) -> str:
        return f"{self.generation:06d}-{self.offset:016d}-{self.length}" + ("-end" if self.end else "")

    @classmethod
    def parse(cls, name: str) -> Part | None:
        found = PART.fullmatch(name)
        return None if found is None else cls(int(found[1]), int(found[2]), int(found[3]), bool(found[4]))


class SharedStore:
    def __init__(self, url: str) -> None:
        try:
            import fsspec
        except ImportError:
            raise ValueError("shared_storage needs fsspec: pip install -e '.[cluster]'") from None
        self.url = url.rstrip("/")
        self.fs, self.root = fsspec.core.url_to_fs(self.url)
        with uploading(f"create {self.url}"):
            self.fs.makedirs(self.root, exist_ok=True)

    def path(self, name: str) -> str:
        return f"{self.root}/{name}"

    def put(self, name: str, data: bytes) -> None:
        """``name`` holds ``data`` whole, or what it held before (a temporary object, then a move)."""
        temporary = self.path(name + ".tmp")
        with uploading(f"upload {name}"):
            self.fs.pipe_file(temporary, data)
            self.fs.mv(temporary, self.path(name))

    def get(self, name: str) -> bytes | None:
        try:
            with uploading(f"download {name}"):
                return self.fs.cat_file(self.path(name))
        except FileNotFoundError:
            return None

    def remove(self, name: str) -> None:
        with uploading(f"remove {name}"):
            if self.fs.exists(self.path(name)):
                self.fs.rm(self.path(name), recursive=True)

    def recording(self, name: str) -> RecordingParts:
        return RecordingParts(self, name)

    def fetch(self, session_id: str, directory: Path) -> bool:
        """The session's checkpoint and its recording as far as it was uploaded, into ``directory``, where
        ``Registry.resume`` reads them; False if the store holds no checkpoint (no open session)."""
        recording = directory / f"{session_id}.mcap"
        saved = self.get(checkpoint.path_for(recording).name)
        if saved is None:
            return False
        directory.mkdir(parents=True, exist_ok=True)
        recording.write_bytes(self.recording(recording.name).assemble())
        checkpoint.write_atomically(checkpoint.path_for(recording), saved)
        log.info("session %s: checkpoint and recording fetched from %s", session_id, self.url)
        return True


class RecordingParts:
    """One recording's parts in the store: uploaded as a flush commits them, put together to resume."""

    def __init__(self, store: SharedStore, name: str) -> None:
        self.store = store
        self.name = name
        self.folder = store.path(name + ".parts")
        self.generation = max((part.generation + 1 for part in self._listed()), default=0)
        self.published = False

    def _listed(self) -> list[Part]:
        with uploading(f"list {self.name}"):
            if not self.store.fs.exists(self.folder):
                return []
            names = [entry.rsplit("/", 1)[-1] for entry in self.store.fs.ls(self.folder, detail=False)]
        return sorted(part for name in names if (part := Part.parse(name)) is not None)

    def add(self, offset: int, data: bytes, end: bool) -> None:
        """Upload the bytes a flush committed at ``offset``; the first part of a generation retires the older."""
        if not data and not end:
            return
        part = Part(self.generation, offset, len(data), end)
        with uploading(f"upload part of {self.name}"):
            if offset == 0:
                self.store.fs.makedirs(self.folder, exist_ok=True)  # a filesystem's folder; nothing on object stores
            self.store.fs.pipe_file(f"{self.folder}/{part.name}", data)
        if offset == 0:
            self._retire_older()

    def _retire_older(self) -> None:
        """Remove the parts of older generations; one left behind is harmless (``assemble`` takes the newest)."""
        try:
            for old in self._listed():
                if old.generation < self.generation:
                    with uploading(f"remove an old part of {self.name}"):
                        self.store.fs.rm(f"{self.folder}/{old.name}")
        except OSError as error:
            log.warning("%s: older parts not removed: %s", self.name, error)

    def assemble(self) -> bytes:
        """The newest generation's parts that follow each other whole from offset 0, then a provisional end
        unless they hold a finished file: a complete MCAP, as a crash leaves a local recording."""
        parts = self._listed()
        newest = max((part.generation for part in parts if part.offset == 0), default=None)
        data = bytearray()
        for part in (part for part in parts if part.generation == newest):
            if part.offset != len(data):
                break
            with uploading(f"download part of {self.name}"):
                chunk = self.store.fs.cat_file(f"{self.folder}/{part.name}")
            if len(chunk) != part.length:
                log.warning("%s: part at %d is cut short (%d of %d bytes); the recording ends before it", self.name,
                            part.offset, len(chunk), part.length)
                break
            data += chunk
            if part.end:
                return bytes(data)
        return bytes(data) + PROVISIONAL_END

    def publish(self, finished: Path) -> None:
        """The closed recording as ``<name>`` in the store, then its parts removed."""
        if self.published:
            return
        self.store.put(self.name, finished.read_bytes())
        self.store.remove(self.name + ".parts")
        self.published = True
