"""Where a dataset's frames are, given its folder or the folder above it.

Downloads unpack to ``scene/data/...`` (the shared Replica and 7-Scenes copies), ``scene/room0/...`` or
straight into ``scene/``; a user passes whichever folder they see first. So a layout is looked for in the
folder itself, then in its ``data/`` subfolder, then in its other subfolders, where exactly one must hold
one.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from ogmapping.datasets.replica import is_replica
from ogmapping.datasets.scannet import is_scannet
from ogmapping.datasets.sevenscenes import DEPTH_PATTERN
from ogmapping.datasets.tum import is_tum


def is_sevenscenes(path: Path) -> bool:
    return any(DEPTH_PATTERN.match(p.name) for p in path.iterdir())


LAYOUTS: tuple[tuple[str, Callable[[Path], bool]], ...] = (
    ("tum", is_tum), ("scannet", is_scannet), ("replica", is_replica), ("7scenes", is_sevenscenes),
)


def layout_of(folder: Path, format: str = "auto") -> str | None:
    """The layout ``folder`` itself has (only ``format``'s, unless auto), None for none."""
    for name, check in LAYOUTS:
        if format in ("auto", name) and check(folder):
            return name
    return None


def locate(root: Path, format: str = "auto") -> tuple[str, Path] | None:
    """The format and the folder of the one dataset at ``root``, its ``data/`` or another subfolder; None
    where none holds one, ValueError where several subfolders do."""
    for folder in (root, root / "data"):
        if folder.is_dir() and (name := layout_of(folder, format)) is not None:
            return name, folder
    found = [(name, folder) for folder in sorted(root.iterdir()) if folder.is_dir()
             and (name := layout_of(folder, format)) is not None]
    if len(found) > 1:
        listed = ", ".join(f"{folder.name} ({name})" for name, folder in found)
        raise ValueError(f"several datasets under {root}: {listed}; pass the one to use")
    return found[0] if found else None
