"""The presets, each as the values it sets over the sections' defaults (dotted keys).

``dense`` and ``sparse`` are the paper's dense and sparse versions, ``sparse-fast`` its faster
sparse one; each line says why where the value is not the paper's or not obvious, with the
bench/RESULTS.md section that holds the measurements.
"""

from __future__ import annotations

from typing import Any

from ogmapping.config.overrides import assign
from ogmapping.config.sections import MapperConfig

# How each setting follows the first frame's step multiple (``ogmapping.config.resolution``: x1 up to about
# 900x510, x2 at 1200x680), per preset; a setting a preset leaves out keeps its value at every size. Every
# rule was fitted on Replica room0 0-19 at 1200x680, the one set at that size (bench/RESULTS.md, the section
# named on each line); nothing below about 900x510 changes.
RESOLUTION_RULES: dict[str, dict[str, str]] = {
    # The step counts times the multiple, in `dense` times its square: 21 steps a frame on Replica room0,
    # within the paper's 5.6 FPS at 8 ms a step ("Steps by resolution", "Four times the steps in `dense`").
    "steps": {"dense": "area", "sparse": "linear", "sparse-fast": "linear"},
    # Gaussians per anchor: an anchor's Gaussians stand for a fixed patch of surface, which a finer image sees
    # as more pixels; `sparse` takes twenty at 1200x680 ("Gaussians by resolution", "Growth by resolution").
    "n_offsets": {"dense": "linear", "sparse": "area", "sparse-fast": "linear"},
    # The hash grid's finest cells half the size at 1200x680 ("Hash grid by resolution").
    "hash_max_resolution": {"dense": "linear"},
    # Anchor colours pay at 1200x680, where twice the steps a frame learn them ("Anchor colours by resolution").
    "anchor_colour": {"sparse-fast": "true from 2"},
    # 6 mm anchors too at 1200x680 ("Octree levels by resolution").
    "max_level": {"dense": "2 from 2", "sparse": "2 from 2"},
    # A finer image holds finer structure, which the L1 term spread over more pixels barely asks for: the SSIM
    # weight times the multiple's square in `dense` (LPIPS 0.054 to 0.040, "SSIM by area"), `dense`'s weight
    # in `sparse` (its own 0.1 was chosen for speed on small images: 36.55 to 38.13 dB with the threshold
    # below, "Growth by resolution").
    "ssim": {"dense": "area", "sparse": "0.8 from 2", "sparse-fast": "linear"},
    # The growth threshold divided by the multiple: the anchors that draw the edges a finer image resolves
    # grow only where the threshold lets them ("Growth by resolution").
    "grad_threshold": {"dense": "inverse", "sparse": "inverse", "sparse-fast": "inverse"},
    # `sparse-fast` averages the map only at 1200x680, where an average no longer lags a map of few steps
    # ("Map averaging by resolution").
    "average_decay": {"sparse-fast": "0.85 from 2"},
}


def _rules(preset_name: str) -> dict[str, str]:
    """``preset_name``'s column of ``RESOLUTION_RULES`` as dotted keys."""
    return {f"resolution.{setting}": rules[preset_name] for setting, rules in RESOLUTION_RULES.items()
            if preset_name in rules}


_DENSE_AND_SPARSE: dict[str, Any] = {
    "octree.max_level": 1,  # 2.5 cm anchors, no 6 mm ones, which carry little of the colour ("Octree levels")
    "optim.average_decay": 0.85,  # queries see the map averaged over about its last 7 steps ("Map averaging")
    "optim.average_growth": 0.015,  # ...and over 1.5% of its steps once it is older ("Map averaging")
    "refine.grad_threshold": 1.5e-4,  # grows more anchors than Scaffold-GS's 2e-4 ("Growth and pruning")
}

PRESET_VALUES: dict[str, dict[str, Any]] = {
    "dense": {
        **_DENSE_AND_SPARSE,
        "model.initial_visible": 0.95,  # no seed lottery of the first Gaussians' opacity ("Visible start")
        "keyframes.global_count": 2,  # worth the tenth of the speed it costs ("Keyframes and the window")
        **_rules("dense"),
    },
    "sparse": {
        **_DENSE_AND_SPARSE,
        "model.encoding": "anchor",
        "refine.prune_opacity": 0.05,
        "keyframes.iterations": 10,  # a step more than nine gains at little cost ("Keyframes and the window")
        "keyframes.first_iterations": 80,  # the anchor colours need more on the first keyframe ("Anchor colours")
        # Four global keyframes at full size (a whole run forgets less: "A whole run"); a streamed frame's
        # steps capped at four renders, so one step on a full window instead of two ("Keyframes and the window").
        "keyframes.global_count": 4,
        "keyframes.frame_renders": 4,
        "keyframes.global_draw": "stalest",  # every region revisited in turn: +0.17 / +0.27 dB held out ("A whole run")
        "loss.ssim": 0.1,  # its gradients drive growth: fewer anchors pay for the window's fifth view ("Loss weights")
        "loss.view": 0.5,  # once the window is full, the view weighs half a window keyframe ("Loss weights")
        "optim.second_moment_decay": 0.99,  # where the camera returns, the map learns as fast as where it is new:
        # +0.14 / +0.16 dB held out on 7-Scenes 0-299 / 300-599, +0.29 on 0-599's lowest stretch ("Adam's memory")
        # Keyframe poses refined in the windows that draw them, at a quarter of the tracking rates, no tracking,
        # the streamed view at its given pose, and each correction reviewed in turn against its client's pose:
        # the map agrees with itself over a whole run, and a render of a frame's time moves with the nearest
        # keyframe ("Keyframe poses refined in the window", "Corrections reviewed").
        "poses.refine": True,
        "poses.track_iterations": 0,
        "poses.track_newton_iterations": 0,
        "poses.view_steps": False,
        "poses.mapping_rate": 0.25,
        "poses.review": True,
        **_rules("sparse"),
    },
    "sparse-fast": {
        "model.encoding": "anchor",
        "model.anchor_colour": False,  # slower and not better with so few steps ("Anchor colours")
        # No average (it lags a map of few steps: "Map averaging"), but at 1200x680: see RESOLUTION_RULES.
        "refine.prune_opacity": 0.05,
        "keyframes.window_scale": 0.5,  # the window's global keyframes at half size ("Keyframes and the window")
        "keyframes.iterations": 6,  # fewer steps than sparse, as the paper's sparse-fast
        "keyframes.frame_iterations": 1,
        "loss.depth": 1.0,  # fewer steps leave depth less converged ("Loss weights")
        **_rules("sparse-fast"),
    },
}

PRESETS = tuple(PRESET_VALUES)


def preset(name: str) -> MapperConfig:
    """The configuration of a named preset."""
    if name not in PRESET_VALUES:
        raise ValueError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
    config = MapperConfig()
    assign(config, PRESET_VALUES[name], "preset")
    return config
