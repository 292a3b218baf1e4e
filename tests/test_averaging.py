"""The map's moving average (``optim.average_decay``): debiased per anchor row, carried through growth,
pruning, snapshots and checkpoints, and what every query sees while training steps the live map."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ogmapping.config import resolve
from ogmapping.mapper import Mapper
from ogmapping.optim.averaging import MapAverage, newest_weight
from ogmapping.persist import snapshot
from ogmapping.quality.evaluation import open_frames
from ogmapping.structure.anchors import AnchorMap

TINY = {"keyframes.first_iterations": "6", "keyframes.iterations": "2"}


def _anchors(count: int, anchors: AnchorMap | None = None) -> AnchorMap:
    anchors = anchors or AnchorMap(2, 4, True, torch.device("cpu"), with_colours=True)
    codes = torch.arange(len(anchors), len(anchors) + count)
    anchors.add(codes, torch.zeros(count, dtype=torch.int64), torch.zeros(count, 3), torch.ones(count),
                torch.zeros(count, 4), None)
    return anchors


def test_the_first_update_copies_the_value_and_later_ones_weigh_as_a_debiased_average():
    assert torch.allclose(newest_weight(torch.tensor([1, 2, 3]), 0.5), torch.tensor([1.0, 2 / 3, 4 / 7]))
    anchors = _anchors(1)
    average = MapAverage(anchors, torch.nn.Linear(1, 1), 0.5)
    seen = []
    for value in (4.0, 1.0, 7.0):
        with torch.no_grad():
            anchors.features.fill_(value)
        average.update()
        seen.append(value)
        weights = [0.5 ** age for age in range(len(seen))][::-1]
        expected = sum(w * v for w, v in zip(weights, seen, strict=True)) / sum(weights)
        assert anchors.averages["features"][0, 0].item() == pytest.approx(expected)


def test_the_horizon_grows_with_the_map_once_it_is_old_enough():
    """With ``growth`` the average covers max(1 / (1 - decay), growth x steps) steps: a young map keeps
    the fixed decay, an old one averages over a share of its steps; without it the decay never moves."""
    growing = MapAverage(_anchors(1), torch.nn.Linear(1, 1), 0.8, growth=0.01)
    assert growing.decay_at(1) == growing.decay_at(500) == 0.8  # 0.01 x 500 steps = 5 = 1 / (1 - 0.8)
    assert growing.decay_at(1000) == pytest.approx(0.9)  # a horizon of 10 steps
    assert growing.decay_at(2000) == pytest.approx(0.95)
    fixed = MapAverage(_anchors(1), torch.nn.Linear(1, 1), 0.8)
    assert fixed.decay_at(1) == fixed.decay_at(10**6) == 0.8


def test_rows_grown_later_average_only_their_own_steps_and_pruning_keeps_rows_in_step():
    anchors = _anchors(2)
    average = MapAverage(anchors, torch.nn.Linear(1, 1), 0.9)
    with torch.no_grad():
        anchors.offsets.fill_(1.0)
    average.update()
    _anchors(1, anchors)  # a grown row: never averaged, so queries see its live value
    with torch.no_grad():
        anchors.offsets.fill_(3.0)
    with average.applied():
        assert anchors.offsets[:2].eq(1.0).all() and anchors.offsets[2].eq(3.0).all()
    assert anchors.offsets.eq(3.0).all()  # the live values are back after the block
    average.update()
    assert anchors.average_steps.tolist() == [2, 2, 1]
    assert anchors.averages["offsets"][2].eq(3.0).all()  # its first update copied the value
    anchors.keep(torch.tensor([False, True, True]), None, 2)
    assert anchors.average_steps.tolist() == [2, 1]
    assert anchors.averages["offsets"].shape == anchors.offsets.shape


def _mapped(overrides: dict[str, str], frames: int = 3) -> tuple[Mapper, list]:
    source = open_frames("synthetic", "synthetic", f"0:{frames + 2}", 1, 0.25, n_frames=40)
    loaded = [source.load(position) for position in range(frames + 2)]
    mapper = Mapper(resolve("sparse-fast", overrides={**TINY, **overrides}))
    for frame in loaded[:frames]:
        mapper.process(frame)
    return mapper, loaded


def test_queries_and_snapshots_see_the_average_and_training_the_live_map():
    mapper, loaded = _mapped({"optim.average_decay": "0.9"})
    live = mapper.model.anchors.offsets.detach().clone()
    pose, camera = loaded[1].c2w, loaded[1].color_intrinsics
    rendered = mapper.render(pose, camera)
    assert torch.equal(mapper.model.anchors.offsets, live)
    with mapper.lock, torch.no_grad(), mapper.model.average.applied():
        assert not torch.equal(mapper.model.anchors.offsets, live)
    restored = Mapper.from_state(mapper.state())  # what a snapshot holds, at full precision
    assert np.array_equal(restored.render(pose, camera).color, rendered.color)
    off, _ = _mapped({})
    assert not np.array_equal(off.render(pose, camera).color, rendered.color)


def test_a_checkpoint_carries_the_average_and_resumes_it_exactly():
    original, loaded = _mapped({"optim.average_decay": "0.8"})
    data = snapshot.encode(original.state(training_state=True), half=False)
    resumed = Mapper.from_state(snapshot.decode(data), training_state=True)
    assert torch.equal(resumed.model.anchors.average_steps, original.model.anchors.average_steps)
    for frame in loaded[3:]:
        original.process(frame)
        resumed.process(frame)
    pose, camera = loaded[4].c2w, loaded[4].color_intrinsics
    assert np.array_equal(resumed.render(pose, camera).color, original.render(pose, camera).color)


def test_a_checkpoint_written_before_the_average_was_kept_starts_it_afresh():
    original, loaded = _mapped({"optim.average_decay": "0.8"})
    state = original.state(training_state=True)
    state.tensors = {name: value for name, value in state.tensors.items() if "average" not in name}
    resumed = Mapper.from_state(state, training_state=True)
    assert int(resumed.model.anchors.average_steps.sum()) == 0 and resumed.model.average.decoder_steps == 0
    steps = resumed.process(loaded[3]).iterations
    assert resumed.model.average.decoder_steps == steps and int(resumed.model.anchors.average_steps.max()) == steps
