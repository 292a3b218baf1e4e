"""Commands as a user pastes them into a fresh shell: the venv's own entry points by path, since the
venv is rarely activated where the output is read."""

from __future__ import annotations

import os
import sys
from pathlib import Path


def command(name: str) -> str:
    """``name`` (ogclient, ogmap, ogserver) as a path to this interpreter's copy, relative to the working
    directory where it lies below it (``.venv/bin/ogclient``); the bare name where none is installed."""
    script = Path(sys.executable).parent / name
    if not script.exists():
        return name
    relative = os.path.relpath(script)
    return relative if not relative.startswith("..") else str(script)
