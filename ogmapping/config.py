"""Every tunable value, as dataclasses, with the presets ``dense``, ``sparse`` and ``sparse-fast``.

Overrides use dotted keys (``keyframes.iterations=40``) from the command line, or a YAML/JSON file
holding the same nesting. ``resolve`` is the one place a preset plus override values, as text (the
command line, the service's ``map<string,string>``) or typed (a YAML/JSON file, code), become a
``MapperConfig``: ``ogmap``, ``ogclient`` (checking locally before it sends the overrides as text)
and the server all call it, so they accept and refuse the same values with the same messages.
Values the paper does not give follow Scaffold-GS / H2-Mapping, tuned for this engine where noted
in docs/method.md.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from ogmapping.backends import BACKENDS


@dataclass
class ModelConfig:
    encoding: str = "hash"  # "hash" (dense version) or "anchor" (sparse version: a feature per anchor)
    n_offsets: int = 5  # Scaffold-GS uses 10; 5 renders as well here at half the cost (bench/RESULTS.md)
    feature_dim: int = 32
    hidden_dim: int = 32
    hash_levels: int = 8
    hash_features_per_level: int = 4
    hash_log2_size: int = 19
    hash_min_resolution: float = 4.0  # cells per metre at the coarsest hash level
    hash_max_resolution: float = 128.0  # cells per metre at the finest hash level


@dataclass
class OctreeConfig:
    voxel_size: float = 0.1  # gamma_0, metres: the coarsest anchor level
    max_level: int = 2  # finest anchor level; gamma_{l+1} = gamma_l / 4
    depth_min: float = 0.1
    depth_max: float = 5.0
    allocation_stride: int = 0  # back-project every n-th pixel per axis when allocating; 0: by resolution
    allocation: str = "octree"  # map densification: octree (paper), unique (naive), projection (SplaTAM)


@dataclass
class KeyframeConfig:
    overlap_threshold: float = 0.8  # a frame becomes a keyframe when N_overlap / N_union is below this
    local_threshold: float = 0.3  # rho_w: keyframes overlapping K_new at least this much are "local"
    local_count: int = 1  # b1
    global_count: int = 1  # b2
    iterations: int = 15  # k: optimisation iterations per new keyframe
    first_iterations: int = 60  # iterations on the very first keyframe
    frame_iterations: int = 2  # iterations on a streamed frame that is not a keyframe (window around it)
    window_scale: float = 1.0  # image scale for the window's global keyframes (the view and local ones: full)
    window_min_width: int = 160  # ...but never narrower than this many pixels (or the keyframe itself)
    window: str = "dynamic"  # dynamic (paper), or a fixed window: random (ESLAM), overlap, coverage


@dataclass
class RefineConfig:
    interval: int = 10  # m: grow and prune every m iterations
    grad_threshold: float = 0.0002  # tau_0 on the mean screen-space gradient (NDC units, as 3DGS and Scaffold-GS)
    min_observations: int = 3  # a Gaussian's gradient is trusted after this many renders
    prune_opacity: float = 0.01  # rho: an anchor whose Gaussians all stay below it is removed
    prune_min_observations: int = 10  # anchors seen fewer times are never pruned
    max_new_anchors: int = 20000  # cap per growth step, keeps one step bounded
    growth: str = "anchor"  # anchor (paper's progressive growth), error (Scaffold-GS), none


@dataclass
class LossConfig:
    color: float = 0.8
    ssim: float = 0.2
    depth: float = 0.5
    scale: float = 0.01


@dataclass
class OptimConfig:
    # Four times Scaffold-GS's rates: it trains for 30k iterations, an online map gets a few per
    # frame (Replica room0 0-19 at 600x340: +1.0 dB streamed at equal cost, bench/RESULTS.md).
    offsets_lr: float = 0.04
    features_lr: float = 0.03
    scaling_lr: float = 0.028
    hash_lr: float = 0.01
    opacity_mlp_lr: float = 0.008
    color_mlp_lr: float = 0.032
    cov_mlp_lr: float = 0.016


@dataclass
class MapperConfig:
    model: ModelConfig = field(default_factory=ModelConfig)
    octree: OctreeConfig = field(default_factory=OctreeConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    backend: str = "auto"  # auto or one of backends.BACKENDS; on the CPU only "cpu" runs the compiled kernels
    seed: int = 0

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> MapperConfig:
        config = cls()
        apply_overrides(config, flatten(data))
        return config


PRESETS = ("dense", "sparse", "sparse-fast")


def preset(name: str) -> MapperConfig:
    """The configuration of a named preset."""
    config = MapperConfig()
    if name == "dense":
        return config
    if name in ("sparse", "sparse-fast"):
        config.model.encoding = "anchor"
        config.refine.prune_opacity = 0.05
        # The window's global keyframes at half size, 9 steps per keyframe: on 7-Scenes 0-299 at
        # 320x240 above 5 FPS (bench/RESULTS.md).
        config.keyframes.window_scale = 0.5
        config.keyframes.iterations = 9
        # Two steps per streamed frame keep 7-Scenes 0-299 at 320x240 above 5 FPS; three gave
        # +0.3 dB there (+0.6 dB on Replica room0 at 600x340) at 3.8-4.7 FPS (bench/RESULTS.md).
        config.keyframes.frame_iterations = 2
        if name == "sparse-fast":
            # Half of sparse's iterations, as the paper's sparse-fast.
            config.keyframes.iterations = 6
            config.keyframes.frame_iterations = 1
        return config
    raise ValueError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")


def flatten(data: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}``."""
    flat: dict[str, Any] = {}
    for key, value in data.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            flat.update(flatten(value, f"{name}."))
        else:
            flat[name] = value
    return flat


def _coerce(value: Any, current: Any, key: str) -> Any:
    """Convert an override to the type of the field it replaces."""
    kind = type(current)
    if isinstance(value, str):
        if kind is bool:
            lowered = value.lower()
            if lowered not in ("true", "false", "1", "0", "yes", "no"):
                raise ValueError(f"config {key} expects true/false, got {value!r}")
            return lowered in ("true", "1", "yes")
        try:
            return kind(value)
        except ValueError as error:
            raise ValueError(f"config {key} expects {kind.__name__}, got {value!r}") from error
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise ValueError(f"config {key} expects {kind.__name__}, got {value!r}")
    return value


def apply_overrides(config: MapperConfig, overrides: dict[str, Any]) -> MapperConfig:
    """Set dotted keys on ``config`` in place; unknown keys and wrong types raise ValueError."""
    for key, value in overrides.items():
        target: Any = config
        parts = key.split(".")
        for part in parts[:-1]:
            if not dataclasses.is_dataclass(target) or not hasattr(target, part):
                raise ValueError(f"unknown config section {key!r}")
            target = getattr(target, part)
        leaf = parts[-1]
        names = {f.name for f in dataclasses.fields(target)} if dataclasses.is_dataclass(target) else set()
        if leaf not in names or dataclasses.is_dataclass(getattr(target, leaf)):
            raise ValueError(f"unknown config key {key!r}")
        setattr(target, leaf, _coerce(value, getattr(target, leaf), key))
    validate(config)
    return config


def parse_override_args(items: list[str]) -> dict[str, str]:
    """``["a.b=1", ...]`` -> ``{"a.b": "1"}``."""
    parsed = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"override {item!r} is not of the form section.key=value")
        parsed[key.strip()] = value.strip()
    return parsed


def load_file(path: str | Path) -> dict[str, Any]:
    """Read a YAML or JSON override file into a flat dict."""
    text = Path(path).read_text()
    data = json.loads(text) if str(path).endswith(".json") else yaml.safe_load(text)
    if not isinstance(data, dict):
        raise ValueError(f"config file {path} must hold a mapping")
    return flatten(data)


def resolve(
    preset_name: str, config_file: str | Path | None = None, overrides: dict[str, Any] | None = None
) -> MapperConfig:
    """The preset, then the file's keys, then ``overrides`` (which win over the file's), checked once as a whole.

    Values may be text or typed; unknown keys, wrong types and out-of-range values raise ValueError
    naming the key.
    """
    requested = load_file(config_file) if config_file else {}
    requested.update(overrides or {})
    return apply_overrides(preset(preset_name), requested)


# The ablation switches (paper section 4); the first value of each is the paper's method.
ALLOCATIONS = ("octree", "unique", "projection")
GROWTHS = ("anchor", "error", "none")
WINDOWS = ("dynamic", "random", "overlap", "coverage")


def validate(config: MapperConfig) -> None:
    """Reject values the engine cannot run with, naming the key."""
    if config.model.encoding not in ("hash", "anchor"):
        raise ValueError(f"model.encoding must be 'hash' or 'anchor', got {config.model.encoding!r}")
    checks = {
        "model.n_offsets": config.model.n_offsets >= 1,
        "model.feature_dim": config.model.feature_dim >= 1,
        "octree.voxel_size": config.octree.voxel_size > 0,
        "octree.max_level": 0 <= config.octree.max_level <= 4,
        "octree.depth_max": config.octree.depth_max > config.octree.depth_min >= 0,
        "octree.allocation_stride": config.octree.allocation_stride >= 0,
        "keyframes.overlap_threshold": 0 < config.keyframes.overlap_threshold <= 1,
        "keyframes.iterations": config.keyframes.iterations >= 0,
        "keyframes.frame_iterations": config.keyframes.frame_iterations >= 0,
        "keyframes.local_count": config.keyframes.local_count >= 0,
        "keyframes.global_count": config.keyframes.global_count >= 0,
        "keyframes.window_scale": 0 < config.keyframes.window_scale <= 1,
        "keyframes.window_min_width": config.keyframes.window_min_width >= 1,
        "refine.interval": config.refine.interval >= 1,
        "refine.prune_opacity": 0 <= config.refine.prune_opacity < 1,
    }
    for key, ok in checks.items():
        if not ok:
            raise ValueError(f"config {key} is out of range")
    for key, value, allowed in (
        ("octree.allocation", config.octree.allocation, ALLOCATIONS),
        ("refine.growth", config.refine.growth, GROWTHS),
        ("keyframes.window", config.keyframes.window, WINDOWS),
    ):
        if value not in allowed:
            raise ValueError(f"config {key} must be one of {', '.join(allowed)}, got {value!r}")
    backends = ("auto", *BACKENDS)
    if config.backend not in backends:
        raise ValueError(f"backend must be {', '.join(backends[:-1])} or {backends[-1]}, got {config.backend!r}")
