"""Operators in a mapping step that make the host wait for the device, by where the engine dispatches them.

On CUDA an operator whose output size or value the host must know (``nonzero``, ``item``, ``unique``,
boolean-mask indexing, ``masked_select``, ``repeat_interleave`` without an output size) stops the host until
the device has caught up, so the step cannot run ahead of the GPU. Counted here on the CPU, below autograd,
by the engine's line that dispatched each one. A steady step (no growth, no pruning) may make only the waits
listed in STEADY, each a known site the static-shape step has still to remove; growth and pruning steps are
counted against their own bar.
"""

from __future__ import annotations

import traceback
from collections import Counter

import pytest
import torch
from steady_step import mapped
from torch.utils._python_dispatch import TorchDispatchMode

from ogmapping.quality.evaluation import open_frames
from ogmapping.runtime.host_read import reads
from ogmapping.runtime.threads import torch_threads

WAITING = {"aten.nonzero.default", "aten._local_scalar_dense.default", "aten._unique2.default",
           "aten.unique_dim.default", "aten.unique_consecutive.default", "aten.masked_select.default",
           "aten.repeat_interleave.Tensor"}
# Per steady step of a three-view window: the frustum test's nonzero per view; `dense` also encodes each anchor
# the window sees once, through a unique over the views' rows; and torch's Adam reads each parameter's step
# count on the host (16 parameters in `sparse`, 15 in the others; on CUDA those counts stay on the host, so
# they are host reads, not waits on the device).
ADAM = ("aten._local_scalar_dense.default", "mapping/steps.py:step")
FRUSTUM = ("aten.nonzero.default", "model/gaussians.py:anchors_in_view")
STEADY = {
    "sparse": {FRUSTUM: 3, ADAM: 16},
    "sparse-fast": {FRUSTUM: 3, ADAM: 15},
    "dense": {FRUSTUM: 3, ADAM: 15, ("aten._unique2.default", "mapping/model.py:window_features"): 1},
}


class HostWaits(TorchDispatchMode):
    """Every host-waiting operator dispatched, with the engine function that dispatched it; those a frame's pose
    tracking and review dispatch (``Tracker.track`` and ``review``, the map held fixed) apart, in ``tracking``."""

    def __init__(self) -> None:
        super().__init__()
        self.sites: Counter[tuple[str, str]] = Counter()
        self.tracking: Counter[tuple[str, str]] = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = str(func)
        boolean_index = name.startswith("aten.index") and any(
            isinstance(index, torch.Tensor) and index.dtype == torch.bool for index in _indices(args))
        if name in WAITING or boolean_index:
            stack = traceback.extract_stack()
            tracking = any(frame.filename.endswith("mapping/tracker.py") and frame.name in ("track", "review")
                           for frame in stack)
            (self.tracking if tracking else self.sites)[name, _engine_site(stack)] += 1
        return func(*args, **(kwargs or {}))


def _indices(args: tuple) -> list:
    return list(args[1]) if len(args) > 1 and isinstance(args[1], (list, tuple)) else []


def _engine_site(stack: traceback.StackSummary) -> str:
    """``folder/module.py:function`` of the innermost engine frame on ``stack``."""
    for frame in reversed(stack):
        if "/ogmapping/" in frame.filename:
            return f"{frame.filename.split('/ogmapping/')[-1]}:{frame.name}"
    return "outside the engine"


def waits_per_steady_step(preset: str, step: str, steps: int = 3) -> dict[tuple[str, str], float]:
    """Host waits per step by site, over ``steps`` steps that neither grow nor prune, after one uncounted."""
    mapper, view, window = mapped(preset, {"refine.interval": "10000"}, step=step)
    waits = HostWaits()
    with torch_threads(mapper.profile.threads):
        mapper.steps.step(view, window)
        with waits:
            for _ in range(steps):
                mapper.steps.step(view, window)
    return {site: count / steps for site, count in waits.sites.items()}


@pytest.mark.parametrize("preset", STEADY)
def test_a_steady_step_waits_only_at_the_listed_sites(preset: str) -> None:
    per_step = waits_per_steady_step(preset, "dynamic")
    assert per_step == STEADY[preset], f"{preset}: host waits per steady step by site: {per_step}"


@pytest.mark.parametrize("preset", STEADY)
def test_a_steady_step_with_static_shapes_never_waits(preset: str) -> None:
    per_step = waits_per_steady_step(preset, "static")
    assert not per_step, f"{preset}: host waits per steady step with static shapes: {per_step}"


def test_a_step_that_refines_and_clamps_poses_never_waits_with_static_shapes():
    """The window keyframes' pose corrections step and are clamped to their bound on the device: refinement in
    the mapping steps adds no wait (a bound of a micrometre clamps every step)."""
    overrides = {"refine.interval": "10000", "poses.refine": "true", "poses.track_iterations": "0",
                 "poses.track_newton_iterations": "0", "poses.max_translation": "1e-6"}
    mapper, view, window = mapped("sparse", overrides, step="static")
    corrections = [keyframe.correction for keyframe in window if keyframe.correction is not None]
    assert corrections, "the window refines a pose"
    waits = HostWaits()
    with torch_threads(mapper.profile.threads), waits:
        for _ in range(2):
            mapper.steps.step(view, window)
    assert not waits.sites, dict(waits.sites)
    assert all(correction.clamped and correction.translation.norm() <= 1e-6 * (1 + 1e-5)
               for correction in corrections)


def test_growth_and_pruning_read_the_device_once():
    """Growth and pruning select with fixed sizes and read how many anchors each level gains and how many go
    in one read (``host_read``), whatever they find."""
    overrides = {"refine.interval": "10000", "refine.grad_threshold": "1e-6", "refine.min_observations": "1"}
    mapper, view, window = mapped("sparse", overrides, step="static")
    with torch_threads(mapper.profile.threads):
        mapper.steps.step(view, window)  # gradients on record
        waits, before, anchors = HostWaits(), reads(), len(mapper.model.anchors)
        with waits:
            grown = mapper.steps._refine()
    assert grown > 0 and len(mapper.model.anchors) != anchors, "the map grew or shrank: the counted pass did its work"
    assert not waits.sites and reads() - before == 1, dict(waits.sites)


@pytest.mark.parametrize("tracked", ["none", "keyframes"])
def test_a_frame_reads_the_device_once_before_its_steps(tracked: str):
    """Per frame: one read for its new cells and keyframe test, one for a keyframe's overlap weights, one per
    refinement, and with ``poses.tracked`` keyframes one for a keyframe's tracking check; no other operator that
    waits (``static`` step, as on a GPU) but in that tracking and in a correction's review (``poses.review``,
    once a frame: it reads nothing), which wait as tracking does."""
    overrides = {"refine.interval": "2", "poses.refine": "false"}
    if tracked == "keyframes":
        overrides = {**overrides, "poses.refine": "true", "poses.tracked": "keyframes", "poses.view_steps": "false",
                     "poses.track_iterations": "2", "poses.track_newton_iterations": "4"}
    mapper, _, _ = mapped("sparse", overrides, step="static")
    frames = open_frames("synthetic", "synthetic", "4:8", scale=0.25)
    waits, before, expected, keyframes = HostWaits(), reads(), 0, 0
    with torch_threads(mapper.profile.threads):
        for position in frames.selection.streamed:
            iterations = mapper.model.iterations
            tracking = sum(waits.tracking.values())
            with waits:
                result = mapper.process(frames.load(position))
            refines = (mapper.model.iterations // 2) - (iterations // 2)
            checked = result.keyframe and tracked == "keyframes"
            expected += 1 + int(result.keyframe) + refines + int(checked)
            assert sum(waits.tracking.values()) > tracking or not checked  # a keyframe's tracking ran
            keyframes += result.keyframe
    assert keyframes, "a keyframe among the frames"
    assert not waits.sites, dict(waits.sites)
    assert reads() - before == expected
