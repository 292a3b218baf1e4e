"""model.initial_visible: the map's first Gaussians start with a chosen share visible, whatever the seed drew."""

import pytest
import torch

from ogmapping.config import resolve
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.mapper import Mapper
from ogmapping.model.gaussians import decoded_logits


def _mapped(preset: str, frames: int, **overrides) -> tuple[Mapper, list]:
    source = SyntheticSource(n_frames=frames, width=64, height=48)
    mapper = Mapper(resolve(preset, overrides={"keyframes.first_iterations": 0, "keyframes.iterations": 0,
                                               "keyframes.frame_iterations": 0, **overrides}))
    for index in range(frames):
        mapper.process(source[index])
    return mapper, [source[index] for index in range(frames)]


def _opacity_logits(mapper: Mapper, rows: torch.Tensor, c2w) -> torch.Tensor:
    with torch.no_grad():
        model = mapper.model
        opacity, _, _ = decoded_logits(model.decoders, model.features(rows), model.anchors.positions[rows],
                                       torch.as_tensor(c2w[:3, 3], dtype=torch.float32))
    return opacity


@pytest.mark.parametrize("preset", ["sparse", "dense"])
@pytest.mark.parametrize("share", [0.25, 0.95])
def test_that_share_of_the_first_anchors_gaussians_starts_visible_in_every_slot(preset, share):
    mapper, frames = _mapped(preset, 1, **{"model.initial_visible": share})
    count = len(mapper.model.anchors)
    assert count > 50
    visible = (_opacity_logits(mapper, torch.arange(count), frames[0].c2w) > 0).float().mean(0)
    assert visible.shape == (mapper.config.model.n_offsets,)
    assert torch.allclose(visible, torch.full_like(visible, share), atol=2 / count), visible


def test_only_the_first_anchors_set_the_start_and_zero_keeps_the_random_one():
    fresh = Mapper(resolve("dense", overrides={"model.initial_visible": 0.9}))
    shifted, _ = _mapped("dense", 3, **{"model.initial_visible": 0.9})
    untouched, _ = _mapped("dense", 3, **{"model.initial_visible": 0.0})
    assert len(shifted.model.anchors) > len(_mapped("dense", 1)[0].model.anchors), "later frames added anchors"
    first_bias = _mapped("dense", 1, **{"model.initial_visible": 0.9})[0].model.decoders.opacity[-1].bias
    assert torch.equal(shifted.model.decoders.opacity[-1].bias, first_bias), "later frames do not shift it again"
    assert not torch.equal(shifted.model.decoders.opacity[-1].bias, fresh.model.decoders.opacity[-1].bias)
    for name, value in fresh.model.decoders.state_dict().items():
        assert torch.equal(untouched.model.decoders.state_dict()[name], value), name
        if name != "opacity.2.bias":
            assert torch.equal(shifted.model.decoders.state_dict()[name], value), name
