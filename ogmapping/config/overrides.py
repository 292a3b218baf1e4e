"""Dotted keys and YAML/JSON files onto a tree of dataclasses: the mapper's config and the server's settings.

A key names a field through its sections (``keyframes.iterations``), or a nested mapping holds the
same path (``{"keyframes": {"iterations": 40}}``); a value must have its field's type (an int for a
float is widened), and where the values arrive as text (the command line, the service's
``map<string,string>``) they are parsed into that type. ``label`` names the tree in every refusal.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

TRUE_WORDS = ("true", "1", "yes")
FALSE_WORDS = ("false", "0", "no")


def flatten(data: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}``."""
    flat: dict[str, Any] = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            flat.update(flatten(value, f"{name}."))
        else:
            flat[name] = value
    return flat


def pinned(preset: str, overrides: Mapping[str, str], resolved_json: str) -> tuple[str, dict[str, str]]:
    """The preset and text overrides that resolve to a recorded config again: every value of the resolved
    config (``MapperConfig.to_dict`` as JSON, "" where a recording lacks it) pinned on top of the recorded
    overrides, so a later version whose presets changed their defaults still rebuilds the recorded map. A
    restored session recorded no preset: with every value pinned, any preset does."""
    text = dict(overrides)
    if resolved_json:
        text.update({key: str(value) for key, value in flatten(json.loads(resolved_json)).items()})
    return preset or "dense", text


def parse_override_args(items: list[str]) -> dict[str, str]:
    """``["a.b=1", ...]`` -> ``{"a.b": "1"}``."""
    parsed = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"override {item!r} is not of the form section.key=value")
        parsed[key.strip()] = value.strip()
    return parsed


def read_mapping(path: str | Path, label: str) -> dict[str, Any]:
    """A YAML or JSON file's top-level mapping (JSON by the ``.json`` suffix, else YAML)."""
    text = Path(path).read_text()
    data = json.loads(text) if str(path).endswith(".json") else yaml.safe_load(text)
    if not isinstance(data, dict):
        raise ValueError(f"{label} file {path} must hold a mapping")
    return data


def assign(target: Any, data: Mapping[str, Any], label: str, *, text: bool = False, prefix: str = "") -> None:
    """Set ``data``'s keys on the dataclass ``target`` in place; unknown keys and wrong types raise
    ValueError naming the key. With ``text``, string values are parsed into their field's type."""
    for key, value in data.items():
        name = f"{prefix}{key}"
        *sections, leaf = key.split(".")
        section = target
        for part in sections:
            section = _field_value(section, part, name, label)
            if not dataclasses.is_dataclass(section):
                raise ValueError(f"unknown {label} key {name!r}")
        current = _field_value(section, leaf, name, label)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, Mapping):
                raise ValueError(f"{label} {name} expects a mapping, got {value!r}")
            assign(current, value, label, text=text, prefix=f"{name}.")
        else:
            setattr(section, leaf, coerce(value, type(current), name, label, text=text))


def _field_value(section: Any, name: str, key: str, label: str) -> Any:
    if name not in {item.name for item in dataclasses.fields(section)}:
        raise ValueError(f"unknown {label} key {key!r}")
    return getattr(section, name)


def coerce(value: Any, kind: type, key: str, label: str, *, text: bool = False) -> Any:
    """``value`` as a ``kind``: an int widened to a float, text parsed when ``text``; anything else of
    another type (a bool for an int included) raises ValueError."""
    if text and isinstance(value, str) and kind is not str:
        if kind is bool:
            lowered = value.lower()
            if lowered not in (*TRUE_WORDS, *FALSE_WORDS):
                raise ValueError(f"{label} {key} expects true/false, got {value!r}")
            return lowered in TRUE_WORDS
        try:
            return kind(value)
        except ValueError as error:
            raise ValueError(f"{label} {key} expects {kind.__name__}, got {value!r}") from error
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if not isinstance(value, kind) or (kind is not bool and isinstance(value, bool)):
        raise ValueError(f"{label} {key} expects {kind.__name__}, got {value!r}")
    return value
