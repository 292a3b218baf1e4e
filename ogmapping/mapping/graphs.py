"""A static-shape step's torch work as compiled graphs (``torch.compile``), the rasterizer between them.

With static shapes (``model.static_gaussians``) nothing in a step's decode, loss, statistics, average,
window keyframes' images, poses or pose corrections' step depends on the map's values for its shapes, so
each part compiles into a graph of a few fused kernels (Inductor; on CUDA replayed as a CUDA graph,
``mode="reduce-overhead"``) instead of hundreds of operators dispatched one by one from Python. The
rasterizer (gsplat's CUDA kernels, the CPU's Numba kernels) runs between the graphs, as it cannot be
traced; so do the dense version's hash grid encoding, whose backward hands its rows to lazy Adam's sink,
and the optimisers (Adam fused).

Each part is the engine's eager definition, compiled: ``StepGraphs(compiled=False)`` hands back the
definitions themselves, so the two can be held equal (tests/test_step_graphs.py). A size that changes
(the anchor buffers' capacity when it doubles, the window's views, an image's) makes torch compile once
more with that size as a symbol, and not again for it.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import torch

from ogmapping.model.static_gaussians import decode_views
from ogmapping.optim import refine
from ogmapping.optim.averaging import fold_in
from ogmapping.optim.keyframes import view_images
from ogmapping.optim.losses import mapping_loss, window_mapping_loss
from ogmapping.optim.window_poses import corrected, window_poses


@dataclass(frozen=True)
class StepGraphs:
    """The parts of a static-shape step, compiled or as defined."""

    decode: Callable  # static_gaussians.decode_views
    view_loss: Callable  # losses.mapping_loss
    window_loss: Callable  # losses.window_mapping_loss
    statistics: Callable  # refine.accumulate_drawn
    average: Callable  # averaging.fold_in
    keyframe_images: Callable  # keyframes.view_images
    poses: Callable  # window_poses.window_poses
    pose_step: Callable  # window_poses.corrected

    @classmethod
    def build(cls, *, compiled: bool, device: torch.device) -> StepGraphs:
        parts = {"decode": decode_views, "view_loss": mapping_loss, "window_loss": window_mapping_loss,
                 "statistics": refine.accumulate_drawn,
                 "average": fold_in, "keyframe_images": view_images, "poses": window_poses, "pose_step": corrected}
        if compiled:
            mode = "reduce-overhead" if device.type == "cuda" else None
            parts = {name: _compiled(part, mode) for name, part in parts.items()}
        return cls(**parts)


def _compiled(part: Callable, mode: str | None) -> Callable:
    """``part`` compiled whole (a graph break is an error), its inputs' sizes free to change: the anchor
    buffers are parameters, whose shapes torch would otherwise take as fixed, recompiling at every doubling."""
    graph = torch.compile(part, mode=mode, fullgraph=True)

    @functools.wraps(part)
    def run(*args, **kwargs):
        with torch._dynamo.config.patch(force_parameter_static_shapes=False,
                                        force_nn_module_property_static_shapes=False):
            return graph(*args, **kwargs)

    return run
