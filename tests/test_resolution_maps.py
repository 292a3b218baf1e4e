"""Mappers under the resolution rules (``ogmapping.config.resolution``): each rule makes the map its value set
by hand makes, the caller's config is left alone, a snapshot keeps the resolved value, and a step multiple of
1 maps exactly as without any rule."""

from __future__ import annotations

import torch

from ogmapping.config import MapperConfig, resolve
from ogmapping.config.resolution import FOLLOWERS
from ogmapping.mapper import Mapper
from ogmapping.persist import snapshot
from ogmapping.quality.evaluation import open_frames

TINY = {"keyframes.first_iterations": "4", "keyframes.iterations": "2"}
NO_RULES = {f"resolution.{name}": "none" for name in FOLLOWERS}
# 80x60 frames against a reference of 1200 pixels: a step multiple of sqrt(4) = 2.
FINE = {**TINY, **NO_RULES, "resolution.reference_pixels": "1200"}


def _frames(count: int):
    frames = open_frames("synthetic", "synthetic", f"0:{count}", 1, 0.25, n_frames=40)  # 80x60
    return [frames.load(position) for position in range(count)]


def _mapped(overrides: dict[str, str]) -> tuple[MapperConfig, Mapper, list]:
    """The caller's config, a mapper made from it, and the two frames it mapped."""
    config = resolve("sparse-fast", overrides=overrides)
    mapper = Mapper(config)
    frames = _frames(2)
    for frame in frames:
        mapper.process(frame)
    return config, mapper, frames


def assert_same_map(mapper: Mapper, overrides: dict[str, str], frames) -> None:
    """``mapper``'s map is the one that ``frames`` make under the values ``overrides`` set by hand."""
    by_hand = Mapper(resolve("sparse-fast", overrides=overrides))
    for frame in frames:
        by_hand.process(frame)
    tensors = by_hand.state().tensors
    assert mapper.state().tensors.keys() == tensors.keys()
    assert all(torch.equal(value, tensors[name]) for name, value in mapper.state().tensors.items())


def assert_resolved_and_kept(config: MapperConfig, mapper: Mapper, name: str) -> None:
    """The caller's rule is left as it was; the mapper's and its snapshot's are resolved."""
    assert getattr(config.resolution, name) != "none"
    assert getattr(mapper.config.resolution, name) == "none"
    assert getattr(Mapper.restore(mapper.snapshot()).config.resolution, name) == "none"


def test_a_multiple_of_one_maps_exactly_as_without_any_rule():
    frames = _frames(2)
    rules = {"resolution.steps": "area", "resolution.n_offsets": "area", "resolution.max_level": "3 from 2",
             "resolution.ssim": "0.8 from 2", "resolution.anchor_colour": "true from 2",
             "resolution.hash_max_resolution": "linear", "resolution.grad_threshold": "inverse",
             "resolution.average_decay": "0.85 from 2"}
    maps = []
    for overrides in ({**TINY, **NO_RULES}, {**TINY, **rules}):
        mapper = Mapper(resolve("sparse-fast", overrides=overrides))
        for frame in frames:
            mapper.process(frame)
        config = mapper.config
        assert (config.model.n_offsets, config.octree.max_level, config.loss.ssim, config.keyframes.step_multiple,
                config.refine.grad_threshold, config.model.anchor_colour, config.optim.average_decay) == \
            (5, 2, 0.2, 1, 2e-4, False, 0)
        maps.append(mapper.state().tensors)
    assert maps[0].keys() == maps[1].keys()
    assert all(torch.equal(value, maps[1][name]) for name, value in maps[0].items())


def test_a_finer_first_frame_builds_more_gaussians_per_anchor_and_the_config_keeps_the_count():
    config, mapper, _ = _mapped({**FINE, "resolution.n_offsets": "linear"})
    assert mapper.model.anchors.offsets.shape[1] == 10 and mapper.model.decoders.n == 10
    assert config.model.n_offsets == 5  # the caller's config is left alone
    assert_resolved_and_kept(config, mapper, "n_offsets")
    assert snapshot.decode(mapper.snapshot()).tensors["anchors.offsets"].shape[1] == 10
    again = Mapper(config)
    for frame in _frames(2):
        again.process(frame)
    # drawn afresh from the seed: the same map
    assert torch.equal(again.model.anchors.offsets, mapper.model.anchors.offsets)


def test_area_builds_gaussians_per_anchor_by_the_square_of_the_multiple():
    overrides = {**FINE, "resolution.n_offsets": "area"}
    config, mapper, frames = _mapped(overrides)
    assert mapper.model.anchors.offsets.shape[1] == 20 and mapper.config.model.n_offsets == 20
    assert config.model.n_offsets == 5
    assert_same_map(mapper, {**FINE, "model.n_offsets": "20"}, frames)


def test_a_fixed_octree_level_from_a_multiple_on_and_the_snapshot_keeps_it():
    config, mapper, _ = _mapped({**FINE, "resolution.max_level": "2 from 2", "octree.max_level": "1"})
    assert mapper.model.octree.max_level == 2 and mapper.config.octree.max_level == 2
    assert mapper.model.decoders.n == 5  # the Gaussians per anchor are left alone
    assert config.octree.max_level == 1
    assert_resolved_and_kept(config, mapper, "max_level")
    assert Mapper.restore(mapper.snapshot()).model.octree.max_level == 2


def test_ssim_follows_the_multiple_linearly_by_area_or_from_a_multiple_on():
    for rule, weight in (("linear", 0.2), ("area", 0.4), ("0.8 from 2", 0.8)):
        overrides = {**FINE, "resolution.ssim": rule, "loss.ssim": "0.1"}
        config, mapper, frames = _mapped(overrides)
        assert mapper.config.loss.ssim == weight and config.loss.ssim == 0.1, rule
        assert mapper.model.decoders.n == 5 and mapper.model.octree.max_level == 2  # the model's shape is kept
        assert_resolved_and_kept(config, mapper, "ssim")
        assert Mapper.restore(mapper.snapshot()).config.loss.ssim == weight
        assert_same_map(mapper, {**FINE, "loss.ssim": str(weight)}, frames)


def test_a_fixed_value_waits_for_its_multiple():
    _, mapper, _ = _mapped({**FINE, "resolution.ssim": "0.8 from 3", "loss.ssim": "0.1"})
    assert mapper.config.loss.ssim == 0.1 and mapper.config.resolution.ssim == "none"


def test_inverse_lowers_the_growth_threshold_as_set_by_hand():
    overrides = {**FINE, "resolution.grad_threshold": "inverse", "refine.grad_threshold": "1.5e-4"}
    config, mapper, frames = _mapped(overrides)
    assert mapper.config.refine.grad_threshold == 0.75e-4 and config.refine.grad_threshold == 1.5e-4
    assert_resolved_and_kept(config, mapper, "grad_threshold")
    assert_same_map(mapper, {**FINE, "refine.grad_threshold": "0.75e-4"}, frames)


def test_anchor_colours_turn_on_as_set_by_hand():
    config, mapper, frames = _mapped({**FINE, "resolution.anchor_colour": "true from 2"})
    assert mapper.model.anchors.with_colours and mapper.config.model.anchor_colour
    assert not config.model.anchor_colour
    assert_resolved_and_kept(config, mapper, "anchor_colour")
    assert Mapper.restore(mapper.snapshot()).model.anchors.with_colours
    assert_same_map(mapper, {**FINE, "model.anchor_colour": "true"}, frames)


def test_the_other_average_decay_as_set_by_hand():
    config, mapper, frames = _mapped({**FINE, "resolution.average_decay": "0.85 from 2"})
    assert mapper.model.average.enabled and mapper.config.optim.average_decay == 0.85
    assert config.optim.average_decay == 0
    assert_resolved_and_kept(config, mapper, "average_decay")
    assert Mapper.restore(mapper.snapshot()).model.average.decay == 0.85
    assert_same_map(mapper, {**FINE, "optim.average_decay": "0.85"}, frames)


def test_a_finer_hash_grid_as_set_by_hand():
    overrides = {**FINE, "model.encoding": "hash", "resolution.hash_max_resolution": "linear"}
    config, mapper, frames = _mapped(overrides)
    assert mapper.config.model.hash_max_resolution == 256 and config.model.hash_max_resolution == 128
    assert_resolved_and_kept(config, mapper, "hash_max_resolution")
    assert_same_map(mapper, {**FINE, "model.encoding": "hash", "model.hash_max_resolution": "256"}, frames)


def test_steps_follow_the_multiple_as_the_counts_set_by_hand():
    for rule, steps in (("linear", 6), ("area", 12)):
        config, mapper, _ = _mapped({**FINE, "resolution.steps": rule, "keyframes.first_iterations": "3"})
        assert mapper.config.keyframes.step_multiple == steps // 3 and config.keyframes.step_multiple == 1
    frames = _frames(2)
    states = []
    for overrides in ({"resolution.steps": "area", "keyframes.first_iterations": "3",
                       "keyframes.frame_iterations": "1"},
                      {"keyframes.first_iterations": "12", "keyframes.frame_iterations": "4"}):
        mapper = Mapper(resolve("sparse-fast", overrides={**FINE, **overrides}), "cpu")
        results = [mapper.process(frame) for frame in frames]
        assert [result.iterations for result in results] == [12, 4]
        states.append(mapper.state().tensors)
    assert states[0].keys() == states[1].keys()
    assert all(torch.equal(value, states[1][name]) for name, value in states[0].items())


def test_each_preset_takes_its_step_multiple_on_a_finer_first_frame():
    for name, factor in (("sparse", 2), ("sparse-fast", 2), ("dense", 4)):
        config = resolve(name, overrides={**TINY, "resolution.reference_pixels": "1200"})  # 80x60: a multiple of 2
        assert Mapper(config).process(_frames(1)[0]).iterations == factor * config.keyframes.first_iterations, name
