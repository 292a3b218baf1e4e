"""The presets, each as the values it sets over the sections' defaults (dotted keys).

``dense`` and ``sparse`` are the paper's dense and sparse versions, ``sparse-fast`` its faster
sparse one; each line says why where the value is not the paper's or not obvious, with the
bench/RESULTS.md section that holds the measurements.
"""

from __future__ import annotations

from typing import Any

from ogmapping.config.overrides import assign
from ogmapping.config.sections import MapperConfig

# Ten Gaussians an anchor, twice the SSIM weight and half the growth threshold at 1200x680, as up to about
# 900x510 below that ("Gaussians by resolution", "SSIM by resolution", "Growth by resolution").
_BY_RESOLUTION: dict[str, Any] = {
    "model.offsets_by_resolution": True,
    "loss.ssim_by_resolution": True,
    "refine.threshold_by_resolution": True,
}

_DENSE_AND_SPARSE: dict[str, Any] = {
    **_BY_RESOLUTION,
    "octree.max_level": 1,  # 2.5 cm anchors, no 6 mm ones, which carry little of the colour ("Octree levels")
    "octree.levels_by_resolution": True,  # ...but 6 mm ones too at 1200x680 ("Octree levels by resolution")
    "optim.average_decay": 0.85,  # queries see the map averaged over about its last 7 steps ("Map averaging")
    "optim.average_growth": 0.015,  # ...and over 1.5% of its steps once it is older ("Map averaging")
    "refine.grad_threshold": 1.5e-4,  # grows more anchors than Scaffold-GS's 2e-4 ("Growth and pruning")
    # The SSIM weight four times its value at 1200x680, not two: LPIPS 0.087 to 0.073 in `sparse`, 0.054
    # to 0.040 in `dense` ("SSIM by area").
    "loss.ssim_growth": "area",
}

PRESET_VALUES: dict[str, dict[str, Any]] = {
    "dense": {
        **_DENSE_AND_SPARSE,
        "model.initial_visible": 0.95,  # no seed lottery of the first Gaussians' opacity ("Visible start")
        "keyframes.global_count": 2,  # worth the tenth of the speed it costs ("Keyframes and the window")
        "model.hash_by_resolution": True,  # cells half the size at 1200x680 ("Hash grid by resolution")
        # Four times the steps at 1200x680, not two: 21 a frame on Replica room0, within the paper's 5.6 FPS
        # at 8 ms a step ("Four times the steps in `dense`").
        "keyframes.steps_growth": "area",
    },
    "sparse": {
        **_DENSE_AND_SPARSE,
        "model.encoding": "anchor",
        "refine.prune_opacity": 0.05,
        "keyframes.iterations": 10,  # a step more than nine gains at little cost ("Keyframes and the window")
        "keyframes.first_iterations": 80,  # the anchor colours need more on the first keyframe ("Anchor colours")
        # Three global keyframes at full size; a streamed frame's steps capped at four renders, so one step
        # on a full window instead of two ("Keyframes and the window").
        "keyframes.global_count": 3,
        "keyframes.frame_renders": 4,
        "loss.ssim": 0.1,  # its gradients drive growth: fewer anchors pay for the window's fifth view ("Loss weights")
        "loss.view": 0.5,  # once the window is full, the view weighs half a window keyframe ("Loss weights")
        # At 1200x680 twenty Gaussians an anchor, not ten, and `dense`'s SSIM weight, not four times its own:
        # with the threshold halved, Replica room0 from 36.55 to 38.13 dB, LPIPS 0.073 to 0.036 ("Growth by
        # resolution").
        "model.offsets_growth": "area",
        "loss.ssim_at_fine_resolution": 0.8,
    },
    "sparse-fast": {
        **_BY_RESOLUTION,
        "model.encoding": "anchor",
        "model.anchor_colour": False,  # slower and not better with so few steps ("Anchor colours")...
        "model.anchor_colour_by_resolution": True,  # ...but pay at 1200x680 ("Anchor colours by resolution")
        # No average below (it lags a map of few steps: "Map averaging"); sparse's and dense's at 1200x680
        # ("Map averaging by resolution").
        "optim.average_decay_by_resolution": 0.85,
        "refine.prune_opacity": 0.05,
        "keyframes.window_scale": 0.5,  # the window's global keyframes at half size ("Keyframes and the window")
        "keyframes.iterations": 6,  # fewer steps than sparse, as the paper's sparse-fast
        "keyframes.frame_iterations": 1,
        "loss.depth": 1.0,  # fewer steps leave depth less converged ("Loss weights")
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
