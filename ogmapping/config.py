"""Every tunable value, as dataclasses, with the presets ``dense``, ``sparse`` and ``sparse-fast``.

Overrides use dotted keys (``keyframes.iterations=40``) from the command line, or a YAML/JSON file
holding the same nesting. ``resolve`` is the one place a preset plus override values, as text (the
command line, the service's ``map<string,string>``) or typed (a YAML/JSON file, code), become a
``MapperConfig``: ``ogmap``, ``ogclient`` (checking locally before it sends the overrides as text)
and the server all call it, so they accept and refuse the same values with the same messages.
Values the paper does not give follow Scaffold-GS / H2-Mapping, tuned for this engine where noted
(the measurements are in bench/RESULTS.md).
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from ogmapping.backends import BACKENDS

MIB = 1 << 20


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
    # A learnable colour logit per anchor, added to the colour decoder's logits for its n Gaussians
    # (not in the paper): a direct, fast-learning colour next to the shared decoder. Started at zero
    # it gains on both benchmarks (7-Scenes 0-299 at 320x240 `sparse` +0.3 dB over four seeds, at
    # about 3/4 of the speed; Replica room0 0-19 at 600x340 +1.1 dB at the same speed; bench/RESULTS.md).
    anchor_colour: bool = True
    # Where a new anchor's colour starts: "zero" (the decoder's colour), or "cell", the mean colour
    # of the allocating frame's depth points in its cell: +1.5 dB more on Replica, but worse on
    # 7-Scenes, whose colour and depth cameras are not registered (cells at depth edges likely start
    # in the wrong colour).
    anchor_colour_start: str = "zero"
    # The share of the map's first Gaussians that start visible: with the first anchors, the opacity
    # decoder's output bias is shifted per slot to that quantile of their logits (tanh opacity > 0 is
    # rendered). 0 keeps nn.Linear's random start (the paper's), under which the share is a lottery of
    # the seed: 5-75% of the first 7-Scenes view over eight seeds of dense, and the seed that drew 5%
    # grew half the anchors and ended 1 dB below the others (bench/RESULTS.md, thirteenth session).
    initial_visible: float = 0.0


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
    frame_renders: int = 0  # caps those steps at this many renders (view + window each), at least one; 0: no cap
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
    # Weight of a step's view (the streamed frame or the new keyframe) in its loss against each window
    # keyframe's 1, once the window is full (it draws all its global keyframes); before, 1 like them.
    view: float = 1.0


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
    colour_lr: float = 0.08  # the anchors' own colour logits (model.anchor_colour); 0.02 and 0.04 gained less
    # Queries see the moving average of the map over its last steps, with this decay per step
    # (ogmapping.optim.averaging); 0: the live map, as the paper.
    average_decay: float = 0.0
    # The average's horizon grows with the map: it covers max(1 / (1 - average_decay), average_growth x
    # steps so far) steps, so an old map averages longer than a young one still converging; 0: fixed.
    average_growth: float = 0.0


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
    # dense and sparse stop refinement at level 1 (2.5 cm anchors, no 6 mm ones; on a 7-Scenes view
    # at 320x240 the Gaussians under 8 px carried 2% of the composited colour). 7-Scenes 0-299 at
    # 320x240: sparse 23.24 against 23.13 dB held-out (four seeds) at the same speed, dense 24.45
    # against 24.46 at 1.26 against 1.13 FPS; Replica room0 0-19 at 600x340: sparse 33.64 against
    # 33.50, dense 33.78 against 34.04. sparse-fast measured the same either way and keeps level 2
    # (eleventh session, bench/RESULTS.md).
    if name in ("dense", "sparse"):
        config.octree.max_level = 1
        # Queries see the map averaged over its last steps (about 7 at 0.85). 7-Scenes 0-299 at
        # 320x240: sparse 23.55 against 23.24 dB held-out (four seeds), dense 24.70 against 24.34
        # (seeds 0-1); Replica room0 0-19 at 600x340: sparse 33.68 / 33.78 against 33.64 / 33.64,
        # dense level; 0.9 and more gain a little more on 7-Scenes but lose Replica, whose frames get
        # fewer steps; sparse-fast (fewer still) loses 0.35 dB there and stays off (twelfth session).
        config.optim.average_decay = 0.85
        # ...and once the map is old enough, over 1.5% of its steps (10 at 700 steps, 15 at 1000): 7-Scenes
        # 0-299 at 320x240 held-out over four seeds sparse 23.60 against 23.55 dB, dense 25.17 against
        # 25.05, every seed better; Replica room0 0-19 (94-114 steps) unchanged (fourteenth session).
        config.optim.average_growth = 0.015
    if name == "dense":
        # Its first Gaussians start 95% visible: 7-Scenes 0-299 at 320x240 24.80 dB held-out over
        # four seeds (24.53-24.99) against 24.41 (23.59-24.96) at 1.62-1.66 against 1.73-1.79 FPS;
        # Replica room0 0-19 at 600x340 33.98 / 34.07 against 33.75 / 33.80. sparse gained 0.07 dB on
        # 7-Scenes and 1.7 dB on Replica but lost 40% of its speed there, under the 2 FPS it must keep.
        config.model.initial_visible = 0.95
        # Grows anchors at a lower screen-gradient mean (tau_0 1.5e-4, not 2e-4): 7-Scenes 0-299 at
        # 320x240 25.05 dB held-out over four seeds (24.77-25.27) against 24.90 (24.75-25.05), every
        # seed level or better, ~18k anchors against ~15k, 1.53-1.69 FPS; Replica room0 0-19 at
        # 600x340 34.46 / 34.53 against 33.98 / 34.07 (fourteenth session, bench/RESULTS.md).
        config.refine.grad_threshold = 1.5e-4
        # Two global keyframes in the window: 7-Scenes 0-299 at 320x240 24.46 / 24.01 dB held-out
        # (seeds 0 / 1) against 23.82 / 23.75 with one, at about a tenth less speed (bench/RESULTS.md).
        config.keyframes.global_count = 2
        return config
    if name in ("sparse", "sparse-fast"):
        config.model.encoding = "anchor"
        config.refine.prune_opacity = 0.05
        # The window's global keyframes at half size (sparse-fast; sparse draws two at full size
        # below), 9 steps per keyframe (bench/RESULTS.md).
        config.keyframes.window_scale = 0.5
        config.keyframes.iterations = 9
        # Two steps per streamed frame; three gave +0.3 dB on 7-Scenes 0-299 at 320x240 (+0.6 dB
        # on Replica room0 at 600x340) at about 20% less speed (fifth session, bench/RESULTS.md).
        config.keyframes.frame_iterations = 2
        if name == "sparse":
            # With anchor colours, 80 steps on the first keyframe: Replica room0 0-19 at 600x340 (one
            # keyframe) 33.47 / 33.50 dB against 32.97 / 33.05 at 60; 20 more steps in a 7-Scenes run of 836.
            config.keyframes.first_iterations = 80
            # Two global keyframes at full size, and a streamed frame's steps capped at four renders:
            # once the window is full that is one step on the view, a local and two global keyframes
            # instead of two on the view, a local and a half-size global one. 7-Scenes 0-299 at 320x240:
            # 23.13 against 22.85 dB held-out (four seeds), depth L1 2.86 against 3.08 cm, at the same
            # speed; Replica (one keyframe, so still two steps a frame) unchanged (bench/RESULTS.md).
            config.keyframes.window_scale = 1.0
            config.keyframes.global_count = 2
            config.keyframes.frame_renders = 4
            # A third global keyframe, the SSIM term at half weight and growth at tau_0 1.5e-4: 7-Scenes 0-299
            # at 320x240 23.94 dB held-out over four seeds against 23.69, at the same speed (4.81-4.83 against
            # 4.77-4.94 FPS in one sitting). The SSIM term's gradients drive growth, so at 0.1 the map grows ~20%
            # fewer anchors, which pays for the window's fifth view. Replica room0 0-19 at 600x340 (one keyframe:
            # no global keyframes) 33.60 / 33.73 against 33.68 / 33.78, SSIM 0.952 (fifteenth session).
            config.keyframes.global_count = 3
            config.loss.ssim = 0.1
            config.refine.grad_threshold = 1.5e-4
            # Once the window is full, the view weighs half as much as each window keyframe: 7-Scenes 0-299 at
            # 320x240 24.09 dB held-out over four seeds (24.04-24.14) against 23.94 (23.74-24.10), every seed
            # better, at the same speed; the window is not full on Replica room0 0-19 (one keyframe) or 7-Scenes
            # 0-59, which stay as they were. Always at 0.5 it cost Replica 0.4 dB (seventeenth session).
            config.loss.view = 0.5
            # ...and ten steps per keyframe, paid for by the faster compiled backward: with the above, 7-Scenes
            # 0-299 at 320x240 24.17 dB held-out over seeds 0-3 and 24.07 over seeds 4-7 (24.09 / 23.93 with nine),
            # 5.31-5.47 FPS against 5.43-5.58 with nine and 5.18-5.23 for the sixteenth session's code in one
            # sitting; Replica room0 0-19 (one keyframe) unchanged (seventeenth session, bench/RESULTS.md).
            config.keyframes.iterations = 10
        if name == "sparse-fast":
            # Half of sparse's iterations, as the paper's sparse-fast.
            config.keyframes.iterations = 6
            config.keyframes.frame_iterations = 1
            # Anchor colours cost sparse-fast on 7-Scenes 0-299 at 320x240: 21.74 against 21.84 dB
            # (seeds 0-1) at 7.1 against 8.5-9.0 FPS, 1.2x the anchors (bench/RESULTS.md).
            config.model.anchor_colour = False
            # Fewer steps leave depth less converged; weighted up, held-out depth L1 on 7-Scenes
            # 0-299 at 320x240 is 2.85 cm against 3.31 cm, below TSDF fusion's 3.25 (bench/RESULTS.md).
            config.loss.depth = 1.0
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


ANCHOR_COLOUR_STARTS = ("zero", "cell")  # model.anchor_colour_start

# The ablation switches (paper section 4); the first value of each is the paper's method.
ALLOCATIONS = ("octree", "unique", "projection")
GROWTHS = ("anchor", "error", "none")
WINDOWS = ("dynamic", "random", "overlap", "coverage")
MAX_OCTREE_LEVEL = 4
# Pixels per axis between allocation samples: wider than any image samples at most one pixel; beyond int64 torch's
# slicing fails (a fuzzed 2^70 once ended a session's frame in an INTERNAL error).
MAX_ALLOCATION_STRIDE = 1 << 16
MAX_HASH_LOG2_SIZE = 30  # 2^30 rows per level: far beyond any bound a server grants, short of int64 trouble
MAX_HASH_RESOLUTION = 1e4  # cells per metre (0.1 mm cells); hashed corner coordinates stay far inside int64
MAX_LOSS_WEIGHT = 1e3
MAX_LEARNING_RATE = 1.0
SEED_RANGE = (-(1 << 63), (1 << 64) - 1)  # what torch.Generator.manual_seed accepts


def _within(value: float, low: float, high: float = math.inf, *, open_low: bool = False) -> bool:
    above = value > low if open_low else value >= low
    return math.isfinite(value) and above and value <= high


def _ranges(config: MapperConfig) -> dict[str, tuple[bool, str]]:
    """Each key's check and the range it states; one entry per key, so a refusal names the key it is about."""
    model, octree, keyframes, refine = config.model, config.octree, config.keyframes, config.refine
    checks: dict[str, tuple[bool, str]] = {
        "model.n_offsets": (model.n_offsets >= 1, ">= 1"),
        "model.feature_dim": (model.feature_dim >= 1, ">= 1"),
        "model.hidden_dim": (model.hidden_dim >= 1, ">= 1"),
        "model.hash_levels": (model.hash_levels >= 1, ">= 1"),
        "model.hash_features_per_level": (model.hash_features_per_level >= 1, ">= 1"),
        "model.initial_visible": (_within(model.initial_visible, 0, 1), "in [0, 1]"),
        "model.hash_log2_size": (1 <= model.hash_log2_size <= MAX_HASH_LOG2_SIZE, f"in [1, {MAX_HASH_LOG2_SIZE}]"),
        "model.hash_min_resolution": (_within(model.hash_min_resolution, 0, MAX_HASH_RESOLUTION, open_low=True),
                                      f"in (0, {MAX_HASH_RESOLUTION:g}]"),
        "model.hash_max_resolution": (_within(model.hash_max_resolution, 0, MAX_HASH_RESOLUTION, open_low=True),
                                      f"in (0, {MAX_HASH_RESOLUTION:g}]"),
        "octree.voxel_size": (_within(octree.voxel_size, 0, open_low=True), "> 0 and finite"),
        "octree.max_level": (0 <= octree.max_level <= MAX_OCTREE_LEVEL, f"in [0, {MAX_OCTREE_LEVEL}]"),
        "octree.depth_min": (_within(octree.depth_min, 0), ">= 0 and finite"),
        "octree.depth_max": (_within(octree.depth_max, octree.depth_min, open_low=True),
                             f"> octree.depth_min ({octree.depth_min:g}) and finite"),
        "octree.allocation_stride": (0 <= octree.allocation_stride <= MAX_ALLOCATION_STRIDE,
                                     f"in [0, {MAX_ALLOCATION_STRIDE}]"),
        "keyframes.overlap_threshold": (_within(keyframes.overlap_threshold, 0, 1, open_low=True), "in (0, 1]"),
        "keyframes.local_threshold": (_within(keyframes.local_threshold, 0, 1), "in [0, 1]"),
        "keyframes.local_count": (keyframes.local_count >= 0, ">= 0"),
        "keyframes.global_count": (keyframes.global_count >= 0, ">= 0"),
        "keyframes.iterations": (keyframes.iterations >= 0, ">= 0"),
        "keyframes.first_iterations": (keyframes.first_iterations >= 0, ">= 0"),
        "keyframes.frame_iterations": (keyframes.frame_iterations >= 0, ">= 0"),
        "keyframes.frame_renders": (keyframes.frame_renders >= 0, ">= 0"),
        "keyframes.window_scale": (_within(keyframes.window_scale, 0, 1, open_low=True), "in (0, 1]"),
        "keyframes.window_min_width": (keyframes.window_min_width >= 1, ">= 1"),
        "refine.interval": (refine.interval >= 1, ">= 1"),
        "refine.grad_threshold": (_within(refine.grad_threshold, 0), ">= 0 and finite"),
        "refine.min_observations": (refine.min_observations >= 0, ">= 0"),
        "refine.prune_opacity": (_within(refine.prune_opacity, 0) and refine.prune_opacity < 1, "in [0, 1)"),
        "refine.prune_min_observations": (refine.prune_min_observations >= 0, ">= 0"),
        "refine.max_new_anchors": (refine.max_new_anchors >= 0, ">= 0"),
        "seed": (SEED_RANGE[0] <= config.seed <= SEED_RANGE[1], f"in [{SEED_RANGE[0]}, {SEED_RANGE[1]}]"),
        # A decay, below 1 (at 1 the average would never move).
        "optim.average_decay": (_within(config.optim.average_decay, 0) and config.optim.average_decay < 1,
                                "in [0, 1)"),
        # A share of the map's steps; 1 would average every step the map has taken.
        "optim.average_growth": (_within(config.optim.average_growth, 0, 1), "in [0, 1]"),
    }
    # Loss weights and learning rates: beyond these the float32 optimisation overflows into NaN or
    # throws Gaussians kilometres per step (Adam's steps are about the learning rate in size).
    for section, high, suffix in (("loss", MAX_LOSS_WEIGHT, ""), ("optim", MAX_LEARNING_RATE, "_lr")):
        for item in dataclasses.fields(getattr(config, section)):
            if item.name.endswith(suffix):
                value = getattr(getattr(config, section), item.name)
                checks[f"{section}.{item.name}"] = (_within(value, 0, high), f"in [0, {high:g}]")
    # The view's weight divides a step's loss, which a view alone would make 0 / 0.
    view = config.loss.view
    checks["loss.view"] = (_within(view, 0, MAX_LOSS_WEIGHT, open_low=True), f"in (0, {MAX_LOSS_WEIGHT:g}]")
    return checks


def validate(config: MapperConfig) -> None:
    """Reject values the engine cannot run with, naming the key and its range."""
    if config.model.encoding not in ("hash", "anchor"):
        raise ValueError(f"model.encoding must be 'hash' or 'anchor', got {config.model.encoding!r}")
    for key, (ok, allowed) in _ranges(config).items():
        if not ok:
            raise ValueError(f"config {key} is out of range: must be {allowed}, got {_value(config, key)!r}")
    for key, value, allowed in (
        ("model.anchor_colour_start", config.model.anchor_colour_start, ANCHOR_COLOUR_STARTS),
        ("octree.allocation", config.octree.allocation, ALLOCATIONS),
        ("refine.growth", config.refine.growth, GROWTHS),
        ("keyframes.window", config.keyframes.window, WINDOWS),
    ):
        if value not in allowed:
            raise ValueError(f"config {key} must be one of {', '.join(allowed)}, got {value!r}")
    backends = ("auto", *BACKENDS)
    if config.backend not in backends:
        raise ValueError(f"backend must be {', '.join(backends[:-1])} or {backends[-1]}, got {config.backend!r}")


def _value(config: MapperConfig, key: str) -> Any:
    target: Any = config
    for part in key.split("."):
        target = getattr(target, part)
    return target


@dataclass
class ConfigBounds:
    """The most one session's config may ask for: what a server grants its clients, on top of
    ``validate``'s ranges. Each bound names the config keys it limits; a server operator tightens
    (or widens) them in the server settings (``config_bounds``)."""

    max_iterations: int = 500  # keyframes.first_iterations, keyframes.iterations, keyframes.frame_iterations
    max_window_keyframes: int = 16  # keyframes.local_count + keyframes.global_count
    max_n_offsets: int = 32  # model.n_offsets
    max_feature_dim: int = 256  # model.feature_dim, model.hidden_dim
    max_hash_levels: int = 32  # model.hash_levels
    max_hash_features_per_level: int = 16  # model.hash_features_per_level
    max_hash_table_mib: int = 256  # model.hash_levels x 2^model.hash_log2_size x hash_features_per_level x 4 bytes
    max_octree_level: int = MAX_OCTREE_LEVEL  # octree.max_level
    min_voxel_size: float = 0.01  # octree.voxel_size, metres: smaller coarse cells mean more anchors
    max_new_anchors: int = 100000  # refine.max_new_anchors

    def validate(self) -> None:
        for item in dataclasses.fields(self):
            value, kind = getattr(self, item.name), type(item.default)
            if isinstance(value, bool) or not isinstance(value, kind) or not _within(value, 0, open_low=True):
                raise ValueError(f"config_bounds.{item.name} must be a positive {kind.__name__} (got {value!r})")

    def check(self, config: MapperConfig) -> None:
        """Raise ValueError naming the first config key beyond these bounds."""
        model, keyframes = config.model, config.keyframes
        limits: list[tuple[str, float, float, str]] = [
            *((f"keyframes.{name}", getattr(keyframes, name), self.max_iterations, "max_iterations")
              for name in ("first_iterations", "iterations", "frame_iterations")),
            ("keyframes.local_count + keyframes.global_count", keyframes.local_count + keyframes.global_count,
             self.max_window_keyframes, "max_window_keyframes"),
            ("model.n_offsets", model.n_offsets, self.max_n_offsets, "max_n_offsets"),
            ("model.feature_dim", model.feature_dim, self.max_feature_dim, "max_feature_dim"),
            ("model.hidden_dim", model.hidden_dim, self.max_feature_dim, "max_feature_dim"),
            ("octree.max_level", config.octree.max_level, self.max_octree_level, "max_octree_level"),
            ("refine.max_new_anchors", config.refine.max_new_anchors, self.max_new_anchors, "max_new_anchors"),
        ]
        if model.encoding == "hash":  # the anchor encoding has no hash table
            limits += [
                ("model.hash_levels", model.hash_levels, self.max_hash_levels, "max_hash_levels"),
                ("model.hash_features_per_level", model.hash_features_per_level, self.max_hash_features_per_level,
                 "max_hash_features_per_level"),
            ]
        for key, value, limit, name in limits:
            if value > limit:
                raise ValueError(f"config {key} = {value} is above this server's limit of {limit} "
                                 f"(config_bounds.{name})")
        if config.octree.voxel_size < self.min_voxel_size:
            raise ValueError(f"config octree.voxel_size = {config.octree.voxel_size} is below this server's "
                             f"limit of {self.min_voxel_size} (config_bounds.min_voxel_size)")
        table_mib = hash_table_bytes(model) / MIB
        if model.encoding == "hash" and table_mib > self.max_hash_table_mib:
            raise ValueError(f"config model.hash_log2_size = {model.hash_log2_size} makes a {table_mib:g} MiB hash "
                             f"table (hash_levels x 2^hash_log2_size x hash_features_per_level x 4 bytes), above "
                             f"this server's limit of {self.max_hash_table_mib} MiB (config_bounds.max_hash_table_mib)")


def hash_table_bytes(model: ModelConfig) -> int:
    """The dense encoding's table (float32); its gradient (rows, or a buffer of the table's size on the CPU) and
    Adam moments take about three times more."""
    return model.hash_levels * 2**model.hash_log2_size * model.hash_features_per_level * 4
