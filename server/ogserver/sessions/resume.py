"""At start-up: bring back the sessions a crashed server left open.

A session's recording ends cleanly only when the session closes (CloseSession, idle expiry, a
graceful shutdown); one without that end belonged to a server that died (kill -9, a crash, a power
cut). Each such session is resumed from its checkpoint (``Registry.resume``); one that cannot be
is logged with the reason and skipped, its files left as they are, and the server serves the others.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from ogapi import recording as layout

from ogserver.recording.checkpoint import SUFFIX
from ogserver.sessions.registry import Registry

log = logging.getLogger(__name__)
LEFTOVERS = ("*.mcap.resumed", f"*{SUFFIX}.tmp")  # a crash while resuming, or while writing a checkpoint


@dataclass
class Resumed:
    sessions: list[str] = field(default_factory=list)
    skipped: dict[str, str] = field(default_factory=dict)  # recording name -> why


def unfinished(record_dir: Path) -> list[Path]:
    """The recordings in ``record_dir`` whose session was still open when its server stopped, oldest first."""
    recordings = []
    for path in record_dir.glob("*.mcap"):
        try:
            if not layout.closed_cleanly(path):
                recordings.append(path)
        except OSError as error:
            log.error("recording %s: cannot read it: %s", path, error)
    return sorted(recordings, key=lambda path: path.stat().st_mtime)


def resume_all(registry: Registry) -> Resumed:
    """Resume every session left open in the record dir; never raises for one session."""
    return resume_each(registry.record_dir, lambda path: registry.resume(path).id)


def resume_each(record_dir: Path, resume: Callable[[Path], str]) -> Resumed:
    """``resume`` (which answers the session's id) each recording left open in ``record_dir``, wherever
    the session goes (this process's registry, or a worker process's)."""
    for pattern in LEFTOVERS:
        for leftover in record_dir.glob(pattern):
            leftover.unlink(missing_ok=True)
    result = Resumed()
    for path in unfinished(record_dir):
        try:
            result.sessions.append(resume(path))
        except Exception as error:  # one session that cannot come back must not keep the server down
            reason = getattr(error, "message", None) or str(error) or type(error).__name__
            result.skipped[path.name] = reason
            log.error("session of %s not resumed: %s (its files are left as they are; `ogclient replay` "
                      "maps its recording into a new session)", path.name, reason)
    if result.sessions or result.skipped:
        log.info("resumed %d sessions left open by the last server, skipped %d", len(result.sessions),
                 len(result.skipped))
    return result
