"""A session's map depends only on its frames and its seed, never on other sessions beside it."""

import torch

from ogmapping.config import resolve
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.mapper import Mapper

OVERRIDES = {"keyframes.iterations": 2, "keyframes.first_iterations": 4, "refine.interval": 2,
             "refine.min_observations": 1}


def _assert_same(left: Mapper, right: Mapper) -> None:
    first, second = left.state().tensors, right.state().tensors
    assert first.keys() == second.keys()
    for name, value in first.items():
        assert torch.equal(value, second[name]), name


def test_interleaved_sessions_map_as_they_would_alone():
    source = SyntheticSource(n_frames=3, width=48, height=36)
    alone = Mapper(resolve("sparse", overrides=OVERRIDES))
    for position in range(len(source)):
        alone.process(source[position])
    mine = Mapper(resolve("sparse", overrides=OVERRIDES))
    for position in range(len(source)):
        mine.process(source[position])
        # A neighbour created mid-stream with another seed, drawing from its own generator.
        neighbour = Mapper(resolve("sparse", overrides={**OVERRIDES, "seed": 7}))
        neighbour.process(source[len(source) - 1 - position])
        torch.rand(1000)
    _assert_same(alone, mine)


def test_the_seed_picks_the_initialisation():
    same = [Mapper(resolve("sparse", overrides={"seed": 3})) for _ in range(2)]
    _assert_same(*same)
    other = Mapper(resolve("sparse", overrides={"seed": 4}))
    assert not torch.equal(same[0].model.decoders.color[0].weight, other.model.decoders.color[0].weight)
