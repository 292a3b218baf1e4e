"""Turn the anchors in view into the Gaussians of one view (only those with positive opacity)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from ogmapping.anchors import AnchorMap
from ogmapping.camera import Intrinsics, in_frustum
from ogmapping.decoders import Decoders

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


def generate(
    anchors: AnchorMap,
    features: Callable[[torch.Tensor], torch.Tensor],
    decoders: Decoders,
    camera_center: torch.Tensor,
    rows: torch.Tensor,
) -> GaussianSet:
    """Decode the n Gaussians of each anchor in ``rows`` as seen from ``camera_center``."""
    positions = anchors.positions[rows]
    to_camera = camera_center.to(positions) - positions
    distances = to_camera.norm(dim=-1, keepdim=True).clamp_min(1e-6)
    decoded = decoders(features(rows), to_camera / distances, distances)
    anchor_scale = torch.exp(anchors.log_scales[rows])  # (V, 3)
    means = positions.unsqueeze(1) + anchors.offsets[rows] * anchor_scale.unsqueeze(1)
    scales = anchor_scale.unsqueeze(1) * decoded.scale_factor
    keep = decoded.opacity > 0
    slot_index = torch.arange(anchors.n_offsets, device=rows.device).expand(rows.shape[0], -1)
    return GaussianSet(
        means=means[keep],
        quats=decoded.quat[keep],
        scales=scales[keep],
        opacities=decoded.opacity[keep],
        colors=decoded.color[keep],
        rows=rows.unsqueeze(1).expand_as(keep)[keep],
        slots=slot_index[keep],
        anchor_rows=rows,
        anchor_opacity=decoded.opacity.detach().amax(dim=1),
    )
