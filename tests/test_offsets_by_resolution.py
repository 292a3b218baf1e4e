"""``model.offsets_by_resolution``, ``model.anchor_colour_by_resolution``, ``model.hash_by_resolution``,
``octree.levels_by_resolution``, ``loss.ssim_by_resolution``, ``loss.ssim_at_fine_resolution``,
``refine.threshold_by_resolution`` and ``optim.average_decay_by_resolution``: Gaussians per anchor, the hash
grid's finest resolution and the SSIM weight times the first frame's step multiple, the growth threshold
divided by it, and anchor colours, one octree level more, another SSIM weight and another average decay
where that multiple is 2 or more."""

from __future__ import annotations

import torch

from ogmapping.config import MapperConfig, resolve
from ogmapping.mapper import Mapper
from ogmapping.persist import snapshot
from ogmapping.quality.evaluation import open_frames

TINY = {"keyframes.first_iterations": "4", "keyframes.iterations": "2"}


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


def test_a_multiple_of_one_maps_exactly_as_without_it():
    frames = _frames(2)
    maps = []
    for scaled in ("false", "true"):
        overrides = {**TINY, "model.offsets_by_resolution": scaled, "octree.levels_by_resolution": scaled,
                     "loss.ssim_by_resolution": scaled, "model.anchor_colour_by_resolution": scaled,
                     "model.hash_by_resolution": scaled, "refine.threshold_by_resolution": scaled,
                     "loss.ssim_at_fine_resolution": "0.8" if scaled == "true" else "0",
                     "optim.average_decay_by_resolution": "0.85" if scaled == "true" else "0"}
        mapper = Mapper(resolve("sparse-fast", overrides=overrides))
        for frame in frames:
            mapper.process(frame)
        assert mapper.config.model.n_offsets == 5 and not mapper.config.model.offsets_by_resolution
        assert mapper.config.octree.max_level == 2 and not mapper.config.octree.levels_by_resolution
        assert mapper.config.loss.ssim == 0.2 and not mapper.config.loss.ssim_by_resolution
        assert mapper.config.loss.ssim_at_fine_resolution == 0
        assert mapper.config.refine.grad_threshold == 2e-4 and not mapper.config.refine.threshold_by_resolution
        assert not mapper.config.model.anchor_colour and not mapper.config.model.anchor_colour_by_resolution
        assert mapper.config.optim.average_decay == 0 and not mapper.config.optim.average_decay_by_resolution
        maps.append(mapper.state().tensors)
    assert maps[0].keys() == maps[1].keys()
    assert all(torch.equal(value, maps[1][name]) for name, value in maps[0].items())


def test_a_finer_first_frame_builds_more_gaussians_per_anchor_and_the_config_keeps_the_count():
    # 80x60 against a reference of 1200 pixels: a linear multiple of sqrt(4) = 2.
    overrides = {**TINY, "model.offsets_by_resolution": "true", "keyframes.steps_reference_pixels": "1200"}
    config, mapper, _ = _mapped(overrides)
    assert mapper.model.anchors.offsets.shape[1] == 10 and mapper.model.decoders.n == 10
    assert config.model.n_offsets == 5 and config.model.offsets_by_resolution  # the caller's config is left alone
    restored = Mapper.restore(mapper.snapshot())
    assert restored.config.model.n_offsets == 10 and not restored.config.model.offsets_by_resolution
    assert snapshot.decode(mapper.snapshot()).tensors["anchors.offsets"].shape[1] == 10
    again = Mapper(config)
    for frame in _frames(2):
        again.process(frame)
    # drawn afresh from the seed: the same map
    assert torch.equal(again.model.anchors.offsets, mapper.model.anchors.offsets)


def test_area_growth_builds_gaussians_per_anchor_by_the_square_of_the_multiple():
    overrides = {**TINY, "model.offsets_by_resolution": "true", "model.offsets_growth": "area",
                 "keyframes.steps_reference_pixels": "1200"}
    config, mapper, frames = _mapped(overrides)
    assert mapper.model.anchors.offsets.shape[1] == 20 and mapper.config.model.n_offsets == 20
    assert config.model.n_offsets == 5  # the caller's config is left alone
    assert_same_map(mapper, {**overrides, "model.offsets_by_resolution": "false", "model.n_offsets": "20"}, frames)


def test_a_finer_first_frame_adds_an_octree_level_and_the_snapshot_keeps_it():
    overrides = {**TINY, "octree.levels_by_resolution": "true", "octree.max_level": "1",
                 "model.offsets_by_resolution": "false", "keyframes.steps_reference_pixels": "1200"}
    config, mapper, _ = _mapped(overrides)
    assert mapper.model.octree.max_level == 2 and mapper.config.octree.max_level == 2
    assert mapper.model.decoders.n == 5  # the Gaussians per anchor are left alone
    assert config.octree.max_level == 1 and config.octree.levels_by_resolution  # the caller's config is left alone
    restored = Mapper.restore(mapper.snapshot())
    assert restored.model.octree.max_level == 2 and not restored.config.octree.levels_by_resolution


def test_a_finer_first_frame_weighs_ssim_more_and_the_snapshot_keeps_the_weight():
    overrides = {**TINY, "loss.ssim_by_resolution": "true", "loss.ssim": "0.1", "model.offsets_by_resolution": "false",
                 "keyframes.steps_reference_pixels": "1200"}
    config, mapper, frames = _mapped(overrides)
    assert mapper.config.loss.ssim == 0.2 and not mapper.config.loss.ssim_by_resolution
    assert mapper.model.decoders.n == 5 and mapper.model.octree.max_level == 2  # the model's shape is left alone
    assert config.loss.ssim == 0.1 and config.loss.ssim_by_resolution  # the caller's config is left alone
    restored = Mapper.restore(mapper.snapshot())
    assert restored.config.loss.ssim == 0.2 and not restored.config.loss.ssim_by_resolution
    assert_same_map(mapper, {**overrides, "loss.ssim_by_resolution": "false", "loss.ssim": "0.2"}, frames)


def test_area_growth_weighs_ssim_by_the_square_of_the_multiple():
    overrides = {**TINY, "loss.ssim_by_resolution": "true", "loss.ssim_growth": "area", "loss.ssim": "0.1",
                 "model.offsets_by_resolution": "false", "keyframes.steps_reference_pixels": "1200"}
    _, mapper, frames = _mapped(overrides)
    assert mapper.config.loss.ssim == 0.4 and not mapper.config.loss.ssim_by_resolution
    assert_same_map(mapper, {**overrides, "loss.ssim_by_resolution": "false", "loss.ssim": "0.4"}, frames)


def test_a_fine_first_frame_takes_the_other_ssim_weight_in_place_of_the_grown_one():
    overrides = {**TINY, "loss.ssim_by_resolution": "true", "loss.ssim_growth": "area", "loss.ssim": "0.1",
                 "loss.ssim_at_fine_resolution": "0.8", "model.offsets_by_resolution": "false",
                 "keyframes.steps_reference_pixels": "1200"}
    config, mapper, frames = _mapped(overrides)
    assert mapper.config.loss.ssim == 0.8 and mapper.config.loss.ssim_at_fine_resolution == 0
    assert config.loss.ssim == 0.1 and config.loss.ssim_at_fine_resolution == 0.8  # the caller's is left alone
    restored = Mapper.restore(mapper.snapshot())
    assert restored.config.loss.ssim == 0.8 and restored.config.loss.ssim_at_fine_resolution == 0
    assert_same_map(mapper, {**overrides, "loss.ssim_by_resolution": "false", "loss.ssim_at_fine_resolution": "0",
                             "loss.ssim": "0.8"}, frames)


def test_a_finer_first_frame_lowers_the_growth_threshold_as_set_by_hand_and_the_snapshot_keeps_it():
    overrides = {**TINY, "refine.threshold_by_resolution": "true", "refine.grad_threshold": "1.5e-4",
                 "model.offsets_by_resolution": "false", "keyframes.steps_reference_pixels": "1200"}
    config, mapper, frames = _mapped(overrides)
    assert mapper.config.refine.grad_threshold == 0.75e-4 and not mapper.config.refine.threshold_by_resolution
    assert mapper.model.decoders.n == 5 and mapper.model.octree.max_level == 2  # the model's shape is left alone
    assert config.refine.grad_threshold == 1.5e-4 and config.refine.threshold_by_resolution  # the caller's is left
    restored = Mapper.restore(mapper.snapshot())
    assert restored.config.refine.grad_threshold == 0.75e-4 and not restored.config.refine.threshold_by_resolution
    assert_same_map(mapper, {**overrides, "refine.threshold_by_resolution": "false",
                             "refine.grad_threshold": "0.75e-4"}, frames)


def test_a_finer_first_frame_turns_anchor_colours_on_as_set_by_hand_and_the_snapshot_keeps_them():
    overrides = {**TINY, "model.anchor_colour_by_resolution": "true", "keyframes.steps_reference_pixels": "1200"}
    config, mapper, frames = _mapped(overrides)
    assert mapper.model.anchors.with_colours and mapper.config.model.anchor_colour
    assert not mapper.config.model.anchor_colour_by_resolution
    assert not config.model.anchor_colour and config.model.anchor_colour_by_resolution  # the caller's is left alone
    restored = Mapper.restore(mapper.snapshot())
    assert restored.model.anchors.with_colours and not restored.config.model.anchor_colour_by_resolution
    assert_same_map(mapper, {**overrides, "model.anchor_colour_by_resolution": "false", "model.anchor_colour": "true"},
                    frames)


def test_a_finer_first_frame_averages_with_the_other_decay_as_set_by_hand_and_the_snapshot_keeps_it():
    overrides = {**TINY, "optim.average_decay_by_resolution": "0.85", "model.offsets_by_resolution": "false",
                 "model.anchor_colour_by_resolution": "false", "keyframes.steps_reference_pixels": "1200"}
    config, mapper, frames = _mapped(overrides)
    assert mapper.model.average.enabled and mapper.config.optim.average_decay == 0.85
    assert not mapper.config.optim.average_decay_by_resolution
    assert config.optim.average_decay == 0 and config.optim.average_decay_by_resolution  # the caller's is left alone
    restored = Mapper.restore(mapper.snapshot())
    assert restored.model.average.decay == 0.85 and not restored.config.optim.average_decay_by_resolution
    assert_same_map(mapper, {**overrides, "optim.average_decay_by_resolution": "0", "optim.average_decay": "0.85"},
                    frames)


def test_a_finer_first_frame_makes_the_hash_grid_finer_as_set_by_hand_and_the_snapshot_keeps_it():
    overrides = {**TINY, "model.encoding": "hash", "model.hash_by_resolution": "true",
                 "model.offsets_by_resolution": "false", "model.anchor_colour_by_resolution": "false",
                 "keyframes.steps_reference_pixels": "1200"}
    config, mapper, frames = _mapped(overrides)
    assert mapper.config.model.hash_max_resolution == 256 and not mapper.config.model.hash_by_resolution
    assert config.model.hash_max_resolution == 128 and config.model.hash_by_resolution  # the caller's is left alone
    restored = Mapper.restore(mapper.snapshot())
    assert restored.config.model.hash_max_resolution == 256 and not restored.config.model.hash_by_resolution
    assert_same_map(mapper, {**overrides, "model.hash_by_resolution": "false", "model.hash_max_resolution": "256"},
                    frames)
