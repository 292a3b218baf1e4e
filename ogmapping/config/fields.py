"""What a config field may hold, declared with the field: a ``Literal`` type lists its choices, a
``Range`` in its metadata bounds its number, a ``Form`` shapes its text; ``check`` reads all three, so
a refusal names the key and what it allows."""

from __future__ import annotations

import dataclasses
import math
import re
import typing
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any, Literal

RANGE = "range"  # the metadata keys
FORM = "form"


@dataclass(frozen=True)
class Range:
    """``low <= value <= high`` (strict where open), finite for floats; ``low`` may name a sibling
    field (``depth_max`` above ``depth_min``)."""

    low: float | str = -math.inf
    high: float = math.inf
    open_low: bool = False
    open_high: bool = False

    def admits(self, value: float, low: float) -> bool:
        if isinstance(value, float) and not math.isfinite(value):
            return False
        above = value > low if self.open_low else value >= low
        below = value < self.high if self.open_high else value <= self.high
        return above and below

    def describe(self, low: float, low_name: str, finite: bool) -> str:
        """``in [0, 1)``, ``>= 1``, ``> 0 and finite``, ``> octree.depth_min (0.1) and finite``."""
        shown = f"{low_name} ({_number(low)})" if low_name else _number(low)
        if self.high == math.inf:
            return f"{'>' if self.open_low else '>='} {shown}" + (" and finite" if finite else "")
        return f"in {'(' if self.open_low else '['}{shown}, {_number(self.high)}{')' if self.open_high else ']'}"


def _number(value: float) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def ranged(default: Any, low: float | str = -math.inf, high: float = math.inf, *,
           open_low: bool = False, open_high: bool = False) -> Any:
    """A dataclass field whose values must lie in ``Range(low, high, ...)``."""
    return dataclasses.field(default=default, metadata={RANGE: Range(low, high, open_low, open_high)})


@dataclass(frozen=True)
class Form:
    """Text that ``pattern`` matches in full, ``shape`` in words for a refusal; a list's items and a
    mapping's values each."""

    pattern: re.Pattern[str]
    shape: str

    def refusal(self, key: str, value: Any) -> str | None:
        """What is wrong with ``value`` under ``key``, or None."""
        for name, text in _texts(key, value):
            if not (isinstance(text, str) and self.pattern.fullmatch(text)):
                return f"{name} must be {self.shape}, got {text!r}"
        return None


def _texts(key: str, value: Any) -> Iterator[tuple[str, Any]]:
    if isinstance(value, Mapping):
        yield from ((f"{key}.{name}", item) for name, item in value.items())
    elif isinstance(value, list):
        yield from ((f"{key}[{index}]", item) for index, item in enumerate(value))
    else:
        yield key, value


def formed(default: Any, pattern: re.Pattern[str], shape: str) -> Any:
    """A dataclass field whose text must have ``Form(pattern, shape)``; a ``default`` of ``list`` or
    ``dict`` makes each instance an empty one of its own."""
    metadata = {FORM: Form(pattern, shape)}
    if default in (list, dict):
        return dataclasses.field(default_factory=default, metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


def choices(hint: Any) -> tuple[Any, ...] | None:
    """A ``Literal`` type's values (nested ones flattened), or None for any other type."""
    return typing.get_args(hint) if typing.get_origin(hint) is Literal else None


def check(section: Any, label: str, prefix: str = "") -> None:
    """Raise ValueError for the first field of the dataclass ``section`` (and its sections, in field
    order) outside its choices, its range or its form."""
    hints = typing.get_type_hints(type(section))
    for item in dataclasses.fields(section):
        key, value = f"{prefix}{item.name}", getattr(section, item.name)
        if dataclasses.is_dataclass(value):
            check(value, label, f"{key}.")
            continue
        allowed = choices(hints[item.name])
        if allowed is not None and value not in allowed:
            raise ValueError(f"{label} {key} must be one of {', '.join(allowed)}, got {value!r}")
        form = item.metadata.get(FORM)
        refusal = form.refusal(key, value) if form is not None else None
        if refusal is not None:
            raise ValueError(f"{label} {refusal}")
        bound = item.metadata.get(RANGE)
        if bound is None:
            continue
        low, low_name = bound.low, ""
        if isinstance(low, str):
            low, low_name = getattr(section, low), f"{prefix}{low}"
        if not bound.admits(value, low):
            described = bound.describe(low, low_name, finite=isinstance(item.default, float))
            raise ValueError(f"{label} {key} is out of range: must be {described}, got {value!r}")
