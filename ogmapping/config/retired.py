"""Keys that configs stored before them may hold, turned into their successors, so that every snapshot and
checkpoint written before still loads (``MapperConfig.from_dict``).

Before one table held how settings follow the image's size (``ogmapping.config.resolution``), each section
had its own switches; a stored config holds them cleared once its first frame resolved them, or pending
when it was stored before any frame.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

# One key, its successor and how its value maps there.
RETIRED_KEYS: dict[str, tuple[str, Callable[[Any], Any]]] = {
    "poses.track_scale": ("poses.track_stride", lambda scale: max(1, round(1 / float(scale)))),
    "keyframes.steps_reference_pixels": ("resolution.reference_pixels", int),
    "keyframes.steps_growth": ("resolution.steps", str),
}
SWITCHES = ("model.offsets_by_resolution", "model.offsets_growth", "model.hash_by_resolution",
            "model.anchor_colour_by_resolution", "octree.levels_by_resolution", "loss.ssim_by_resolution",
            "loss.ssim_growth", "loss.ssim_at_fine_resolution", "refine.threshold_by_resolution",
            "optim.average_decay_by_resolution")
MAX_OCTREE_LEVEL = 4  # what the switch's one level more stopped at


def retire(flat: dict[str, Any]) -> dict[str, Any]:
    """``flat`` (dotted keys) with every retired key replaced by its successor; a successor given too wins."""
    flat = dict(flat)
    for old, (new, convert) in RETIRED_KEYS.items():
        if old in flat:
            flat.setdefault(new, convert(flat.pop(old)))
    if any(key in flat for key in SWITCHES):
        switches = {key: flat.pop(key, None) for key in SWITCHES}
        for name, rule in _rules(switches, flat).items():
            flat.setdefault(f"resolution.{name}", rule)
    return flat


def _rules(switch: dict[str, Any], flat: dict[str, Any]) -> dict[str, str]:
    """The resolution rules the old switches stood for (each applied from a step multiple of 2 on)."""
    rules = {}
    if _on(switch["model.offsets_by_resolution"]):
        rules["n_offsets"] = str(switch["model.offsets_growth"] or "linear")
    if _on(switch["model.hash_by_resolution"]):
        rules["hash_max_resolution"] = "linear"
    if _on(switch["model.anchor_colour_by_resolution"]):
        rules["anchor_colour"] = "true from 2"
    if _on(switch["octree.levels_by_resolution"]):
        rules["max_level"] = f"{min(int(flat.get('octree.max_level', 2)) + 1, MAX_OCTREE_LEVEL)} from 2"
    if float(switch["loss.ssim_at_fine_resolution"] or 0):
        rules["ssim"] = f"{float(switch['loss.ssim_at_fine_resolution'])!r} from 2"
    elif _on(switch["loss.ssim_by_resolution"]):
        rules["ssim"] = str(switch["loss.ssim_growth"] or "linear")
    if _on(switch["refine.threshold_by_resolution"]):
        rules["grad_threshold"] = "inverse"
    if float(switch["optim.average_decay_by_resolution"] or 0):
        rules["average_decay"] = f"{float(switch['optim.average_decay_by_resolution'])!r} from 2"
    return rules


def _on(value: Any) -> bool:
    """A stored switch, typed (JSON) or as text."""
    return str(value).strip().lower() in ("true", "1")
