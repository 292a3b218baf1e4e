"""Every tunable value, as dataclasses, with the presets ``dense``, ``sparse`` and ``sparse-fast``.

Overrides use dotted keys (``keyframes.iterations=40``) from the command line, or a YAML/JSON file
holding the same nesting. ``resolve`` is the one place a preset plus override values, as text (the
command line, the service's ``map<string,string>``) or typed (a YAML/JSON file, code), become a
``MapperConfig``: ``ogmap``, ``ogclient`` (checking locally before it sends the overrides as text)
and the server all call it, so they accept and refuse the same values with the same messages.

The sections and their ranges are in ``sections``, the presets in ``presets``, a server's bounds in
``bounds``, how settings follow a first frame's size in ``resolution``, stored configs' old keys in
``retired``; ``overrides`` is the dotted-key and file mechanism the server's settings share.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ogmapping.config.bounds import MIB, ConfigBounds, hash_table_bytes
from ogmapping.config.overrides import flatten, parse_override_args, pinned, read_mapping
from ogmapping.config.presets import PRESET_VALUES, PRESETS, preset
from ogmapping.config.sections import (
    Allocation,
    AnchorColourStart,
    Backend,
    Encoding,
    GlobalDraw,
    Growth,
    KeyframeConfig,
    LossConfig,
    MapperConfig,
    ModelConfig,
    OctreeConfig,
    OptimConfig,
    PosesConfig,
    RefineConfig,
    RenderConfig,
    Window,
    apply_overrides,
    validate,
)

__all__ = [
    "MIB", "PRESETS", "PRESET_VALUES", "Allocation", "AnchorColourStart", "Backend", "ConfigBounds", "Encoding",
    "GlobalDraw", "Growth", "KeyframeConfig", "LossConfig", "MapperConfig", "ModelConfig", "OctreeConfig",
    "OptimConfig", "PosesConfig", "RefineConfig", "RenderConfig", "Window", "apply_overrides", "flatten",
    "hash_table_bytes", "load_file", "parse_override_args", "pinned", "preset", "resolve", "validate",
]


def load_file(path: str | Path) -> dict[str, Any]:
    """Read a YAML or JSON override file into a flat dict."""
    return flatten(read_mapping(path, "config"))


def resolve(
    preset_name: str,
    config_file: str | Path | None = None,
    overrides: dict[str, Any] | None = None,
    bounds: ConfigBounds | None = None,
) -> MapperConfig:
    """The preset, then the file's keys, then ``overrides`` (which win over the file's), checked once as a whole.

    Values may be text or typed; unknown keys, wrong types, out-of-range values and values beyond
    ``bounds`` (a server's, when given) raise ValueError naming the key.
    """
    requested = load_file(config_file) if config_file else {}
    requested.update(overrides or {})
    config = apply_overrides(preset(preset_name), requested)
    if bounds is not None:
        bounds.check(config)
    return config
