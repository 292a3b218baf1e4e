"""A map's statistics as one typed record, so callers read fields instead of guessing dict keys."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any


@dataclass(frozen=True)
class MapStats:
    """What ``Mapper.stats`` reports: counts of the map and the seconds spent per stage."""

    frames: int
    keyframes: int
    iterations: int
    anchors: int
    anchors_per_level: tuple[int, ...]
    gaussians: int
    octree_cells_per_level: tuple[int, ...]
    device: str
    backend: str
    timings: dict[str, float]

    def to_dict(self) -> dict[str, Any]:
        """The JSON shape of the server's ``engine_json`` and the runner's results (lists, in field order)."""
        return {name: list(value) if isinstance(value, tuple) else value for name, value in asdict(self).items()}
