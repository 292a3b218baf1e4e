"""Turn the anchors in view into the Gaussians of one view (only those with positive opacity)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.geometry import in_frustum
from ogmapping.model.decoders import Decoders, activate
from ogmapping.model.gaussians_cpu import AssembleGaussians
from ogmapping.structure.anchor_colour import with_anchor_colours
from ogmapping.structure.anchors import AnchorMap

FRUSTUM_MARGIN = 0.15  # fraction of the image size; anchors just outside still cast Gaussians inside


@dataclass
class GaussianSet:
    means: torch.Tensor  # (G, 3)
    quats: torch.Tensor  # (G, 4)
    scales: torch.Tensor  # (G, 3)
    opacities: torch.Tensor  # (G,)
    colors: torch.Tensor  # (G, 3)
    rows: torch.Tensor  # (G,) anchor row of each Gaussian
    slots: torch.Tensor  # (G,) offset index within its anchor
    anchor_rows: torch.Tensor  # (V,) anchors in view
    anchor_opacity: torch.Tensor  # (V,) largest decoded opacity per anchor in view

    def __len__(self) -> int:
        return int(self.means.shape[0])


def anchors_in_view(anchors: AnchorMap, intrinsics: Intrinsics, c2w: torch.Tensor, far: float) -> torch.Tensor:
    """Rows of anchors whose centres fall in the (slightly widened) view frustum."""
    margin = FRUSTUM_MARGIN * max(intrinsics.width, intrinsics.height)
    mask = in_frustum(anchors.positions, intrinsics, c2w, near=0.0, far=far, margin=margin)
    return torch.nonzero(mask).squeeze(-1)


def decoded_logits(decoders: Decoders, features: torch.Tensor, positions: torch.Tensor,
                   camera_center: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The decoders' logits for anchors with ``features`` at ``positions``, seen from ``camera_center``
    (the view direction and distance they are conditioned on)."""
    to_camera = camera_center.to(positions) - positions
    distances = to_camera.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    return decoders.logits(features, to_camera / distances, distances)


def generate(
    anchors: AnchorMap,
    features: Callable[[torch.Tensor], torch.Tensor],
    decoders: Decoders,
    camera_center: torch.Tensor,
    rows: torch.Tensor,
    *,
    compiled: bool,
) -> GaussianSet:
    """Decode the n Gaussians of each anchor in ``rows`` as seen from ``camera_center``.

    ``compiled`` assembles them with the Numba kernel of ``gaussians_cpu`` (CPU tensors) instead
    of torch ops; both give the same Gaussians and gradients.
    """
    positions = anchors.positions.index_select(0, rows)
    logits = decoded_logits(decoders, features(rows), positions, camera_center)
    if anchors.with_colours:
        opacity, color, cov = logits
        logits = opacity, with_anchor_colours(color, anchors.colours, rows), cov
    if compiled:
        return _assemble_compiled(anchors, rows, *logits)
    return _assemble_torch(anchors, rows, positions, *logits)


def _assemble_torch(anchors: AnchorMap, rows: torch.Tensor, positions: torch.Tensor, opacity_logits: torch.Tensor,
                    color_logits: torch.Tensor, cov: torch.Tensor) -> GaussianSet:
    """``positions``: the anchors' centres, ``anchors.positions[rows]``."""
    n = anchors.n_offsets
    decoded = activate(opacity_logits, color_logits, cov, n)
    anchor_scale = torch.exp(anchors.log_scales[rows])  # (V, 3)
    means = positions.unsqueeze(1) + anchors.offsets[rows] * anchor_scale.unsqueeze(1)
    scales = anchor_scale.unsqueeze(1) * decoded.scale_factor
    keep = torch.nonzero(decoded.opacity.reshape(-1) > 0).squeeze(-1)  # one nonzero, shared by every gather
    return GaussianSet(
        means=means.reshape(-1, 3)[keep],
        quats=decoded.quat.reshape(-1, 4)[keep],
        scales=scales.reshape(-1, 3)[keep],
        opacities=decoded.opacity.reshape(-1)[keep],
        colors=decoded.color.reshape(-1, 3)[keep],
        rows=rows[keep // n],
        slots=keep % n,
        anchor_rows=rows,
        anchor_opacity=decoded.opacity.detach().amax(dim=1),
    )


def _assemble_compiled(anchors: AnchorMap, rows: torch.Tensor, opacity_logits: torch.Tensor,
                       color_logits: torch.Tensor, cov: torch.Tensor) -> GaussianSet:
    means, quats, scales, opacities, colors, kept_rows, slots, anchor_opacity = AssembleGaussians.apply(
        opacity_logits, color_logits, cov, anchors.positions, anchors.log_scales, anchors.offsets, rows)
    return GaussianSet(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
                       rows=kept_rows, slots=slots, anchor_rows=rows, anchor_opacity=anchor_opacity)
