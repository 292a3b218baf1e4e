"""A mapper a few frames into the synthetic room, and the view and window of its next step: what the tests
that count a step's operators count."""

from __future__ import annotations

import dataclasses

import torch

from ogmapping.config import resolve
from ogmapping.frames.preprocess import prepare
from ogmapping.mapper import Mapper
from ogmapping.optim.keyframes import Keyframe, View
from ogmapping.quality.evaluation import open_frames

MAPPED = 4  # frames mapped before the counted step, two of them keyframes at least


def mapped(preset: str, overrides: dict[str, str], shared_decode: bool = False,
           step: str = "dynamic") -> tuple[Mapper, View, list[Keyframe]]:
    """A ``preset`` mapper (two steps on its first keyframe, one on each later) after MAPPED frames, the next
    frame as a view, and the two newest keyframes as its window (three views a step). ``step`` "static" or
    "compiled" (config ``step``) maps as on a GPU, static shapes and torch ops around the rasterizer (as
    graphs with "compiled"), with the CPU's rasterizer in gsplat's place."""
    frames = open_frames("synthetic", "synthetic", f"0:{MAPPED + 2}", scale=0.25)
    config = resolve(preset, overrides={"keyframes.first_iterations": "2", "keyframes.iterations": "1", **overrides})
    mapper = Mapper(config, "cpu")
    if step != "dynamic":
        mapper.model.profile = dataclasses.replace(mapper.profile, shared_decode=True, static_shapes=True,
                                                   graphs=step == "compiled", compiled=False)
        mapper.model.build(mapper.config)
    else:
        mapper.model.profile = dataclasses.replace(mapper.profile, shared_decode=shared_decode)
    for position in frames.selection.streamed[:MAPPED]:
        mapper.process(frames.load(position))
    frame = prepare(frames.load(frames.selection.streamed[MAPPED]), config.octree.depth_min, config.octree.depth_max)
    as_tensor = lambda array: torch.as_tensor(array, dtype=mapper.profile.precision)  # noqa: E731
    view = View.of(as_tensor(frame.rgb), as_tensor(frame.depth), frame.color_intrinsics, as_tensor(frame.c2w),
                   compiled=mapper.profile.compiled)
    window = mapper.keyframes.keyframes[-2:]
    assert len(window) == 2, "the counted step renders three views"
    return mapper, view, window
