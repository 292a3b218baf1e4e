"""The by-resolution switches: values that a session's first frame resolves from its step multiple.

Each switch (``model.offsets_by_resolution`` and the others in ``sections``) stands for a value that
depends on the image's size. The mapper resolves them once, on its first frame, into plain values kept
in the config, with every switch cleared, so snapshots and checkpoints rebuild the same model. A
multiple of 1 (images up to about 900x510) leaves every value as it was.
"""

from __future__ import annotations

from dataclasses import dataclass

from ogmapping.config.sections import (
    MAX_HASH_RESOLUTION,
    MAX_LOSS_WEIGHT,
    MAX_OCTREE_LEVEL,
    MAX_SCALED_OFFSETS,
    MapperConfig,
    ResolutionGrowth,
)


@dataclass(frozen=True)
class Resolved:
    """What resolving changed beyond plain values, which the mapper has to act on."""

    reshaped: bool = False  # the model's shape or encoding: rebuild it, drawn afresh from the seed
    averaged: bool = False  # the map average's decay: start a new average


def grown(multiple: int, growth: ResolutionGrowth) -> int:
    """What a value that grows with the image is multiplied by: ``multiple`` ("linear"), or its square
    ("area"), as the pixels grow."""
    return multiple * multiple if growth == "area" else multiple


def pending(config: MapperConfig) -> bool:
    """Whether any by-resolution switch of ``config`` is still to resolve."""
    model, loss = config.model, config.loss
    return any((model.offsets_by_resolution, model.anchor_colour_by_resolution, model.hash_by_resolution,
                config.octree.levels_by_resolution, loss.ssim_by_resolution, loss.ssim_at_fine_resolution,
                config.refine.threshold_by_resolution, config.optim.average_decay_by_resolution))


def resolve_switches(config: MapperConfig, multiple: int) -> Resolved:
    """Resolve ``config``'s switches in place for a first frame of step ``multiple``, then clear them:
    ``n_offsets`` (``model.offsets_by_resolution``), the hash grid's finest resolution
    (``model.hash_by_resolution``) and the SSIM weight (``loss.ssim_by_resolution``) times the multiple,
    or ``n_offsets`` and the SSIM weight times its square with ``model.offsets_growth`` or
    ``loss.ssim_growth`` "area"; the SSIM weight ``loss.ssim_at_fine_resolution`` in place of the grown
    one; the growth threshold divided by the multiple (``refine.threshold_by_resolution``); anchor colours
    on (``model.anchor_colour_by_resolution``); one octree level more (``octree.levels_by_resolution``);
    the other average decay (``optim.average_decay_by_resolution``)."""
    model, octree, loss, optim, refine = config.model, config.octree, config.loss, config.optim, config.refine
    offsets, colours, hashed = model.offsets_by_resolution, model.anchor_colour_by_resolution, model.hash_by_resolution
    levels, ssim, fine_ssim = octree.levels_by_resolution, loss.ssim_by_resolution, loss.ssim_at_fine_resolution
    threshold, average = refine.threshold_by_resolution, optim.average_decay_by_resolution
    model.offsets_by_resolution = model.anchor_colour_by_resolution = model.hash_by_resolution = False
    octree.levels_by_resolution = loss.ssim_by_resolution = refine.threshold_by_resolution = False
    optim.average_decay_by_resolution = loss.ssim_at_fine_resolution = 0.0
    if multiple == 1:
        return Resolved()
    if fine_ssim:
        loss.ssim = fine_ssim
    elif ssim:
        loss.ssim = min(loss.ssim * grown(multiple, loss.ssim_growth), MAX_LOSS_WEIGHT)
    if threshold:
        refine.grad_threshold = refine.grad_threshold / multiple
    if average:
        optim.average_decay = average
    if offsets:
        model.n_offsets = min(model.n_offsets * grown(multiple, model.offsets_growth), MAX_SCALED_OFFSETS)
    colours = colours and not model.anchor_colour
    if colours:
        model.anchor_colour = True
    hashed = hashed and model.encoding == "hash"
    if hashed:
        model.hash_max_resolution = min(model.hash_max_resolution * multiple, MAX_HASH_RESOLUTION)
    if levels:
        octree.max_level = min(octree.max_level + 1, MAX_OCTREE_LEVEL)
    return Resolved(reshaped=bool(offsets or colours or hashed or levels), averaged=bool(average))
