"""A map's statistics as one typed record, so callers read fields instead of guessing dict keys."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any


@dataclass(frozen=True)
class PoseSummary:
    """Pose refinement over the keyframes that carry a correction (all but the first): how many, the
    mean and largest correction of the camera centre (metres) and of its rotation (degrees), and how
    many reached the bound and were clamped there."""

    refined_keyframes: int
    mean_correction_m: float
    max_correction_m: float
    mean_correction_deg: float
    max_correction_deg: float
    clamped_keyframes: int


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
    poses: PoseSummary | None = None  # with ``poses.refine``
    # The config the map is built with: after its first frame, what the resolution rules made of it.
    config: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """The JSON shape of the server's ``engine_json`` and the runner's results (lists, in field order;
        ``poses`` only where refinement runs, so other sessions' stats read as they always have; the config
        apart, where those record it)."""
        return {name: list(value) if isinstance(value, tuple) else value for name, value in asdict(self).items()
                if not (name == "poses" and value is None) and name != "config"}
