"""Resolution as one rule: how settings follow the size of a session's images, declared as data.

An image's step multiple is ``sqrt(pixels / resolution.reference_pixels)`` rounded half up, at least 1:
1 up to about 900x510, 2 at 1200x680, 3 at 1920x1080. A finer image of the same scene holds more detail
for the map to learn (bench/RESULTS.md "Steps by resolution" and the sections after it). Each field of
``ResolutionConfig`` but the reference names a setting (``FOLLOWERS``) and holds its rule, as text:

- ``none``: the setting keeps its value;
- ``linear`` / ``area``: its value times the multiple / times its square, at most its cap;
- ``inverse``: its value divided by the multiple;
- ``VALUE from M``: VALUE where the multiple is M or more, else its own value.

``resolve`` applies the rules once, on a session's first frame: a pure function of a config and a
multiple whose result keeps the resolved values with every rule ``none``, so a snapshot or checkpoint
rebuilds the same model. ``ogmap config --preset P --resolution WxH`` prints what it resolves.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Generic, Protocol, TypeVar

from ogmapping.config.fields import RANGE, check, formed, ranged

MAX_SCALED_OFFSETS = 32  # Gaussians per anchor that a rule makes at most
FIXED = re.compile(r"(?P<value>true|false|[-+0-9.eE]+) from (?P<multiple>[1-9][0-9]*)")


@dataclass(frozen=True)
class Follower:
    """A setting that may follow the step multiple: its dotted key, the rules it takes (of ``linear``,
    ``area``, ``inverse``, ``from``), a cap besides its field's own range, and what a new value asks of the
    map: ``reshapes``, a model rebuilt (still empty, drawn afresh from the seed); ``restarts_average``, a
    new moving average."""

    key: str
    kinds: tuple[str, ...]
    cap: float = math.inf
    reshapes: bool = False
    restarts_average: bool = False


FOLLOWERS: dict[str, Follower] = {
    # A frame's four step counts (keyframes.iterations, first_iterations, frame_iterations, frame_renders)
    # are multiplied by keyframes.step_multiple, 1 unless a rule sets it.
    "steps": Follower("keyframes.step_multiple", ("linear", "area", "from")),
    "n_offsets": Follower("model.n_offsets", ("linear", "area", "from"), cap=MAX_SCALED_OFFSETS, reshapes=True),
    "hash_max_resolution": Follower("model.hash_max_resolution", ("linear", "area", "from"), reshapes=True),
    "anchor_colour": Follower("model.anchor_colour", ("from",), reshapes=True),
    "max_level": Follower("octree.max_level", ("from",), reshapes=True),
    "ssim": Follower("loss.ssim", ("linear", "area", "from")),
    "grad_threshold": Follower("refine.grad_threshold", ("inverse", "from")),
    "average_decay": Follower("optim.average_decay", ("from",), restarts_average=True),
}


def _rule(name: str, default: str = "none") -> Any:
    """A rule field for ``FOLLOWERS[name]``: ``none`` or one of the rules it takes."""
    kinds = FOLLOWERS[name].kinds
    words = ["none", *(kind for kind in kinds if kind != "from")]
    pattern = "|".join(words + ([FIXED.pattern] if "from" in kinds else []))
    shape = " or ".join(f"'{word}'" for word in words) + (" or 'VALUE from M'" if "from" in kinds else "")
    return formed(default, re.compile(pattern), shape)


@dataclass
class ResolutionConfig:
    # The pixels of an image of step multiple 1 (600x340's 204,000: x1 up to about 900x510); 0: always 1.
    reference_pixels: int = ranged(204000, 0)
    steps: str = _rule("steps", "linear")
    n_offsets: str = _rule("n_offsets")
    hash_max_resolution: str = _rule("hash_max_resolution")
    anchor_colour: str = _rule("anchor_colour")
    max_level: str = _rule("max_level")
    ssim: str = _rule("ssim")
    grad_threshold: str = _rule("grad_threshold")
    average_decay: str = _rule("average_decay")


class Resolvable(Protocol):
    """A config with resolution rules: ``MapperConfig``, which holds a ``ResolutionConfig`` (so this module
    sits below the sections, which import it)."""

    resolution: ResolutionConfig


Config = TypeVar("Config", bound=Resolvable)


@dataclass(frozen=True)
class Resolution(Generic[Config]):
    """A config resolved for a step ``multiple``, and which followers took a new value."""

    config: Config
    multiple: int
    changed: tuple[str, ...]

    @property
    def reshaped(self) -> bool:
        return any(FOLLOWERS[name].reshapes for name in self.changed)

    @property
    def restarts_average(self) -> bool:
        return any(FOLLOWERS[name].restarts_average for name in self.changed)


def step_multiple(reference_pixels: int, width: int, height: int) -> int:
    """``sqrt(pixels / reference_pixels)`` rounded half up, at least 1; 1 when the reference is 0."""
    if reference_pixels == 0:
        return 1
    return max(1, math.floor(math.sqrt(width * height / reference_pixels) + 0.5))


def pending(config: Resolvable) -> bool:
    """Whether any rule of ``config`` is still to resolve."""
    return any(getattr(config.resolution, name) != "none" for name in FOLLOWERS)


def reshape_pending(config: Resolvable) -> bool:
    """Whether a rule still to resolve may change the model's shape: a map with anchors cannot follow it."""
    return any(getattr(config.resolution, name) != "none" and follower.reshapes
               for name, follower in FOLLOWERS.items())


def resolve(config: Config, multiple: int, caps: Mapping[str, float] | None = None) -> Resolution[Config]:
    """``config`` with every follower at its value for a first frame of step ``multiple`` and every rule
    ``none``; ``config`` itself is left as it is. ``caps`` (a server's, ``ConfigBounds.caps``) bound what a
    rule makes of a follower, by its name, besides the follower's own cap."""
    resolved = copy.deepcopy(config)
    changed = []
    for name, follower in FOLLOWERS.items():
        rule = getattr(config.resolution, name)
        setattr(resolved.resolution, name, "none")
        section, field = _place(resolved, follower.key)
        value = getattr(section, field)
        cap = min(_cap(section, field, follower), (caps or {}).get(name, math.inf))
        new = follow(rule, value, multiple, cap)
        if new != value:
            setattr(section, field, new)
            changed.append(name)
    return Resolution(resolved, multiple, tuple(changed))


def follow(rule: str, value: Any, multiple: int, cap: float = math.inf) -> Any:
    """``value`` under ``rule`` at step ``multiple`` (see the module's docstring)."""
    if rule == "none":
        return value
    if rule in ("linear", "area"):
        return min(value * (multiple * multiple if rule == "area" else multiple), cap)
    if rule == "inverse":
        return value / multiple
    fixed = FIXED.fullmatch(rule)
    if fixed is None:
        raise ValueError(f"unknown resolution rule {rule!r}")
    if multiple < int(fixed["multiple"]):
        return value
    fixed_value = _parsed(fixed["value"], value)
    return fixed_value if isinstance(fixed_value, bool) else min(fixed_value, max(value, cap))


def highest(config: Resolvable, name: str) -> Any:
    """The largest value follower ``name`` can take at any step multiple: what a server's bounds count."""
    follower = FOLLOWERS[name]
    section, field = _place(config, follower.key)
    value, rule = getattr(section, field), getattr(config.resolution, name)
    if rule in ("linear", "area"):
        return max(value, _cap(section, field, follower))
    fixed = FIXED.fullmatch(rule)
    return max(value, _parsed(fixed["value"], value)) if fixed else value


def check_rules(config: Resolvable) -> None:
    """Every ``VALUE from M`` rule's VALUE is a value its setting accepts; ValueError naming the rule if not."""
    for name, follower in FOLLOWERS.items():
        rule = getattr(config.resolution, name)
        fixed = FIXED.fullmatch(rule)
        if fixed is None:
            continue
        section, field = _place(config, follower.key)
        try:
            value = _parsed(fixed["value"], getattr(section, field))
            check(dataclasses.replace(section, **{field: value}), "config", f"{follower.key.split('.')[0]}.")
        except ValueError as error:
            raise ValueError(f"config resolution.{name} = {rule!r}: {error}") from None


def _place(config: Resolvable, key: str) -> tuple[Any, str]:
    section, field = key.split(".")
    return getattr(config, section), field


def _cap(section: Any, field: str, follower: Follower) -> float:
    """The follower's cap, and at most its field's own upper bound."""
    bound = next(item for item in dataclasses.fields(section) if item.name == field).metadata.get(RANGE)
    return min(follower.cap, bound.high) if bound is not None else follower.cap


def _parsed(text: str, like: Any) -> Any:
    """``text`` as a value of ``like``'s type (bool, int or float)."""
    if isinstance(like, bool):
        if text not in ("true", "false"):
            raise ValueError(f"expects true or false, got {text!r}")
        return text == "true"
    try:
        return type(like)(text)
    except ValueError:
        raise ValueError(f"expects {type(like).__name__}, got {text!r}") from None
