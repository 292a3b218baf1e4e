"""Per-keyframe exposure (``keyframes.exposure``): off, nothing is added; on, a keyframe whose image is
darkened or brightened learns (a, b) towards it with the map while the first keyframe stays the
identity, a streamed frame's leaves the optimiser after its steps, and checkpoints keep them."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from ogmapping.config import resolve
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.mapper import Mapper
from ogmapping.optim import exposure
from ogmapping.optim.losses import mapping_loss
from ogmapping.persist import snapshot

STEPS = {"keyframes.first_iterations": 8, "keyframes.iterations": 8, "keyframes.frame_iterations": 1}


def mapper(step: str = "dynamic", on: bool = True, **overrides) -> Mapper:
    return Mapper(resolve("sparse", overrides={**STEPS, "step": step, "keyframes.exposure": on, **overrides}))


def exposure_group(mapper: Mapper) -> list[torch.Tensor]:
    return next(group for group in mapper.model.optimizer.param_groups if group["name"] == exposure.GROUP)["params"]


def test_exposed_is_exp_a_times_colour_plus_b_per_image() -> None:
    colour = torch.rand(4, 5, 3)
    assert torch.equal(exposure.exposed(colour, torch.zeros(2)), colour)
    values = torch.tensor([math.log(0.5), 0.1])
    assert torch.allclose(exposure.exposed(colour, values), 0.5 * colour + 0.1)
    batch = torch.stack([colour, colour])
    both = exposure.exposed(batch, torch.stack([torch.zeros(2), values]))
    assert torch.equal(both[0], colour) and torch.allclose(both[1], 0.5 * colour + 0.1)


def test_the_loss_corrects_the_render_before_colour_and_ssim_only() -> None:
    render, truth = torch.rand(16, 16, 3), torch.rand(16, 16, 3)
    depth, scales = torch.rand(16, 16), torch.rand(5, 3)
    values = torch.tensor([math.log(0.7), 0.05])
    _, plain = mapping_loss(0.7 * render + 0.05, depth, truth, depth, scales, resolve("sparse").loss, compiled=False)
    _, corrected = mapping_loss(render, depth, truth, depth, scales, resolve("sparse").loss, compiled=False,
                                exposure=values)
    for term in ("color", "ssim", "depth", "scale"):
        assert torch.allclose(corrected[term], plain[term], atol=1e-6), term


def test_off_the_optimiser_and_the_keyframes_carry_no_exposure() -> None:
    source = SyntheticSource(n_frames=2, width=32, height=24)
    off = mapper(on=False, **{"keyframes.overlap_threshold": 1.0})
    for position in range(len(source)):
        off.process(source[position])
    assert exposure.GROUP not in [group["name"] for group in off.model.optimizer.param_groups]
    assert len(off.keyframes) == 2 and all(keyframe.exposure is None for keyframe in off.keyframes.keyframes)


@pytest.mark.parametrize("step", ["dynamic", "static"])
@pytest.mark.parametrize(("gain", "offset"), [(0.6, 0.0), (1.0, 0.15)])
def test_a_keyframe_darkened_or_brightened_learns_its_exposure(step: str, gain: float, offset: float) -> None:
    """The second keyframe's image is the first's scene through a known affine: its (a, b) move towards
    (log gain, offset), the first keyframe's stays the identity, outside the optimiser."""
    source = SyntheticSource(n_frames=2, width=48, height=36)
    session = mapper(step, **{"keyframes.overlap_threshold": 1.0})
    session.process(source[0])
    changed = source[1]
    changed = dataclasses.replace(changed, rgb=np.clip(changed.rgb * gain + offset, 0.0, 1.0).astype(np.float32))
    assert session.process(changed).keyframe
    first, second = session.keyframes.keyframes
    assert first.exposure is None
    a, b = second.exposure.values.tolist()
    assert (a < 0) if gain < 1 else (b > 0), (a, b)
    assert [id(param) for param in exposure_group(session)] == [id(second.exposure.values)]


def test_a_streamed_frames_exposure_leaves_the_optimiser_after_its_steps() -> None:
    source = SyntheticSource(n_frames=3, width=32, height=24)
    session = mapper(**{"keyframes.overlap_threshold": 0.01})  # a single keyframe: the others are streamed
    for position in range(len(source)):
        result = session.process(source[position])
    assert not result.keyframe and result.iterations == 1
    assert len(session.keyframes) == 1 and exposure_group(session) == []
    optimizer = session.model.optimizer
    stepped = {id(param) for group in optimizer.param_groups for param in group["params"]}
    assert {id(param) for param in optimizer.state} <= stepped, "Adam keeps no moments of a departed exposure"


def test_a_checkpoint_keeps_each_keyframes_exposure_and_maps_on_exactly() -> None:
    source = SyntheticSource(n_frames=4, width=32, height=24)
    original = mapper(**{"keyframes.overlap_threshold": 1.0, "keyframes.iterations": 3})
    for position in range(2):
        original.process(source[position])
    data = snapshot.encode(original.state(training_state=True), half=False)
    resumed = Mapper.from_state(snapshot.decode(data), training_state=True)
    kept = [None if k.exposure is None else k.exposure.values.tolist() for k in resumed.keyframes.keyframes]
    assert kept == [None if k.exposure is None else k.exposure.values.tolist() for k in original.keyframes.keyframes]
    assert kept[0] is None and all(values != [0.0, 0.0] for values in kept[1:])
    assert [id(p) for p in exposure_group(resumed)] == [id(k.exposure.values) for k in resumed.keyframes.keyframes[1:]]
    for position in range(2, len(source)):
        expected, got = original.process(source[position]), resumed.process(source[position])
        assert got.loss == expected.loss
    assert [k.exposure.values.tolist() for k in resumed.keyframes.keyframes[1:]] == \
        [k.exposure.values.tolist() for k in original.keyframes.keyframes[1:]]


def test_a_checkpoint_without_exposures_loads_them_at_the_identity() -> None:
    source = SyntheticSource(n_frames=2, width=32, height=24)
    original = mapper(**{"keyframes.overlap_threshold": 1.0})
    for position in range(len(source)):
        original.process(source[position])
    state = original.state(training_state=True)
    state.tensors = {name: value for name, value in state.tensors.items() if not name.endswith(".exposure")}
    resumed = Mapper.from_state(state, training_state=True)
    first, second = resumed.keyframes.keyframes
    assert first.exposure is None and second.exposure.values.tolist() == [0.0, 0.0]
    bad = original.state(training_state=True)
    bad.tensors["training.keyframes.1.exposure"] = torch.tensor([math.nan, 0.0], dtype=torch.float64)
    with pytest.raises(ValueError, match="exposure"):
        Mapper.from_state(bad, training_state=True)
