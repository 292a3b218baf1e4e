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
    """Every host-waiting operator dispatched, with the engine function that dispatched it."""

    def __init__(self) -> None:
        super().__init__()
        self.sites: Counter[tuple[str, str]] = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        name = str(func)
        boolean_index = name.startswith("aten.index") and any(
            isinstance(index, torch.Tensor) and index.dtype == torch.bool for index in _indices(args))
        if name in WAITING or boolean_index:
            self.sites[name, _engine_site()] += 1
        return func(*args, **(kwargs or {}))


def _indices(args: tuple) -> list:
    return list(args[1]) if len(args) > 1 and isinstance(args[1], (list, tuple)) else []


def _engine_site() -> str:
    """``folder/module.py:function`` of the innermost engine frame on the stack."""
    for frame in reversed(traceback.extract_stack()):
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


def test_growth_and_pruning_wait_within_their_bar() -> None:
    """Growth and pruning reallocate the rows (a few times per ``refine.interval`` steps): their waits are
    counted apart from the steady step's: 14 on this map (sparse), most in growth's proposals."""
    mapper, _, _ = mapped("sparse", {"refine.interval": "1"})
    waits = HostWaits()
    with torch_threads(mapper.profile.threads), waits:
        mapper.steps._refine()
    assert 0 < sum(waits.sites.values()) <= 20, dict(waits.sites)
