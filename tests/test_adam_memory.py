"""The map's Adam forgets squared gradients at ``optim.second_moment_decay``: its groups, plain or selective,
take the decay; a row the steps leave without a gradient sheds its second moment at that rate; and a
checkpoint's resumed map steps on exactly as the original."""

from __future__ import annotations

import pytest
import torch

from ogmapping.config import resolve
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.mapper import Mapper
from ogmapping.persist import snapshot

STEPS = {"keyframes.first_iterations": 4, "keyframes.iterations": 4, "keyframes.frame_iterations": 1}


def mapper(decay: float, **overrides) -> Mapper:
    return Mapper(resolve("sparse", overrides={**STEPS, "optim.second_moment_decay": decay, **overrides}))


def test_sparse_forgets_faster_than_torchs_default() -> None:
    assert resolve("sparse").optim.second_moment_decay == 0.99
    assert resolve("dense").optim.second_moment_decay == 0.999


@pytest.mark.parametrize("selective", [False, True])
def test_every_group_of_the_maps_adam_takes_the_decay(selective: bool) -> None:
    optimizer = mapper(0.95, **{"optim.selective": selective}).model.optimizer
    assert {group["betas"] for group in optimizer.param_groups} == {(0.9, 0.95)}


@pytest.mark.parametrize("decay", [0.9, 0.99])
def test_a_row_left_without_gradients_sheds_its_second_moment_at_the_decay(decay: float) -> None:
    source = SyntheticSource(n_frames=1, width=32, height=24)
    live = mapper(decay)
    live.process(source[0])
    optimizer = live.model.optimizer
    features = live.model.anchors.parameter("features")
    before = optimizer.state[features]["exp_avg_sq"].clone()
    assert before.abs().sum() > 0
    for parameter in (p for group in optimizer.param_groups for p in group["params"]):
        parameter.grad = torch.zeros_like(parameter)
    for _ in range(3):
        optimizer.step()
    torch.testing.assert_close(optimizer.state[features]["exp_avg_sq"], before * decay**3)


def test_a_resumed_map_keeps_the_decay_and_maps_on_exactly() -> None:
    source = SyntheticSource(n_frames=3, width=32, height=24)
    original = mapper(0.99)
    original.process(source[0])
    data = snapshot.encode(original.state(training_state=True), half=False)
    resumed = Mapper.from_state(snapshot.decode(data), training_state=True)
    assert {group["betas"] for group in resumed.model.optimizer.param_groups} == {(0.9, 0.99)}
    for position in range(1, len(source)):
        assert resumed.process(source[position]).loss == original.process(source[position]).loss
