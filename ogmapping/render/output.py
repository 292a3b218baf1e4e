"""What every backend returns, and the one way to finish it from composited sums."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch


@dataclass
class RenderOutput:
    """What a backend returns.

    ``color`` (H, W, 3) is composited over ``background``; ``depth`` (H, W) is the expected depth
    (accumulated z divided by alpha, 0 where alpha is 0); ``alpha`` (H, W) the accumulated opacity.
    ``means2d`` (N, 2) holds the projected centres in pixels; after ``loss.backward()`` its
    ``.grad`` is the per-Gaussian screen-space gradient refinement uses. ``visible`` (N,) marks
    Gaussians that touched the image. ``absgrad``, where the backend computes it (gsplat with
    ``RasterOptions.absgrad``), reads after ``backward`` each Gaussian's sum over pixels of |gradient|.
    """

    color: torch.Tensor
    depth: torch.Tensor
    alpha: torch.Tensor
    means2d: torch.Tensor
    visible: torch.Tensor
    absgrad: Callable[[], torch.Tensor | None] | None = None

    def screen_gradient(self, absolute: bool = False) -> torch.Tensor | None:
        """After ``backward``: ``means2d.grad`` (N, 2), or with ``absolute`` the sum over pixels of |gradient|
        (``absgrad``; None where the backend does not compute it). None for a render without gradients."""
        if not self.means2d.requires_grad:
            return None
        if absolute:
            return self.absgrad() if self.absgrad is not None else None
        return self.means2d.grad


def finish_output(
    color: torch.Tensor, accum_depth: torch.Tensor, alpha: torch.Tensor, means2d: torch.Tensor, radii: torch.Tensor
) -> RenderOutput:
    """Assemble the shared output from a view's images, projected centres and radii; expected depth is
    accumulated depth over alpha, in torch."""
    covered = alpha > 0
    depth = torch.where(covered, accum_depth / torch.where(covered, alpha, torch.ones_like(alpha)), 0.0)
    return RenderOutput(color=color, depth=depth, alpha=alpha, means2d=means2d, visible=radii > 0)

