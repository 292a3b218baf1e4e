"""A step's Gaussians with shapes that do not depend on the map's values: every row of the anchor
buffers, in every view, with the ones not drawn made inert.

The dynamic decode (``gaussians.generate_window``) selects the anchors in view and the Gaussians of
positive opacity with ``nonzero``: each selection's size is read on the host, so on CUDA the host
waits for the device twice per view and a step cannot be captured as a graph. Here each view decodes
all ``capacity`` rows of the anchor buffers, and a Gaussian is drawn where its anchor is live and in
the view's frustum and its opacity is positive; the others get opacity 0 and no gradient, which every
rasterizer composites as nothing. Shapes change only when the buffers' capacity does.

The drawn Gaussians' values and gradients are the dynamic decode's (the decoders run over more rows,
so sums over rows round in another order); a drawn Gaussian's anchor row and slot follow from its
index (row = index // n, slot = index % n), so the refinement statistics are plain sums over the
buffers (``refine.accumulate_drawn``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.geometry import in_frustum
from ogmapping.model.decoders import Decoders, activate
from ogmapping.model.gaussians import FRUSTUM_MARGIN, GaussianSet, decoded_logits
from ogmapping.structure.anchor_colour import with_anchor_colours
from ogmapping.structure.anchors import AnchorMap


@dataclass
class DrawnGaussianSet(GaussianSet):
    """A view's Gaussians for every buffer row (G = capacity * n), with which of them are drawn."""

    drawn: torch.Tensor  # (G,) bool: live anchor in view and positive opacity
    in_view: torch.Tensor  # (capacity,) bool: live anchors in the view's frustum

    def drawn_count(self) -> torch.Tensor:
        """How many Gaussians the view draws, on the device (reading it makes the host wait)."""
        return self.drawn.sum()


def view_mask(anchors: AnchorMap, intrinsics: Intrinsics, c2w: torch.Tensor, far: float) -> torch.Tensor:
    """(capacity,) live anchors whose centres fall in the (slightly widened) view frustum."""
    margin = FRUSTUM_MARGIN * max(intrinsics.width, intrinsics.height)
    return in_frustum(anchors.buffer("positions"), intrinsics, c2w, near=0.0, far=far, margin=margin) & anchors.live


def decode_views(anchors: AnchorMap, features: torch.Tensor, decoders: Decoders, poses: list[torch.Tensor],
                 intrinsics: list[Intrinsics], far: float) -> list[DrawnGaussianSet]:
    """The Gaussians of every buffer row as seen from each camera-to-world ``poses[i]`` with ``intrinsics[i]``,
    those of anchors in its frustum (out to ``far``) drawn: ``view_mask`` and ``generate_drawn``."""
    masks = [view_mask(anchors, camera, pose, far) for pose, camera in zip(poses, intrinsics, strict=True)]
    return generate_drawn(anchors, features, decoders, [pose[:3, 3] for pose in poses], masks)


def generate_drawn(
    anchors: AnchorMap,
    features: torch.Tensor,
    decoders: Decoders,
    camera_centers: list[torch.Tensor],
    in_view: list[torch.Tensor],
) -> list[DrawnGaussianSet]:
    """Each view's Gaussians of every buffer row, view i seen from ``camera_centers[i]`` with the anchors
    of ``in_view[i]`` (``view_mask``) drawn; ``features`` holds every row's decoder features. The
    decoders run once over all (row, view) pairs."""
    views, capacity = len(camera_centers), anchors.capacity
    positions = anchors.buffer("positions")
    all_positions = positions.repeat(views, 1)
    centers = torch.stack([center.to(positions) for center in camera_centers])
    centers = centers.unsqueeze(1).expand(views, capacity, 3).reshape(-1, 3)
    rows = _all_rows(capacity, views, positions.device)
    opacity, color, cov = decoded_logits(decoders, features.repeat(views, 1), all_positions, centers)
    if anchors.with_colours:
        color = with_anchor_colours(color, anchors.parameter("colours"), rows)
    n = anchors.n_offsets
    decoded = activate(opacity, color, cov, n)
    anchor_scale = torch.exp(anchors.parameter("log_scales")).repeat(views, 1)  # (V * C, 3)
    means = all_positions.unsqueeze(1) + anchors.parameter("offsets").repeat(views, 1, 1) * anchor_scale.unsqueeze(1)
    scales = anchor_scale.unsqueeze(1) * decoded.scale_factor
    seen = torch.stack(in_view).reshape(-1)  # (V * C,)
    drawn = (opacity > 0) & seen.unsqueeze(1)
    # where, not a product: a Gaussian not drawn passes no gradient back, as one left out would not
    opacities = torch.where(drawn, decoded.opacity, 0.0)
    anchor_opacity = decoded.opacity.detach().amax(dim=1)
    per_view = capacity * n
    index = torch.arange(per_view, device=positions.device)
    own_rows, slots = index // n, index % n
    parts = {
        "means": means.reshape(views, per_view, 3), "quats": decoded.quat.reshape(views, per_view, 4),
        "scales": scales.reshape(views, per_view, 3), "opacities": opacities.reshape(views, per_view),
        "colors": decoded.color.reshape(views, per_view, 3), "drawn": drawn.reshape(views, per_view),
        "anchor_opacity": anchor_opacity.view(views, capacity),
    }
    return [DrawnGaussianSet(**{name: part[view] for name, part in parts.items()}, rows=own_rows, slots=slots,
                             anchor_rows=rows[:capacity], in_view=in_view[view])
            for view in range(views)]


def _all_rows(capacity: int, views: int, device: torch.device) -> torch.Tensor:
    """0..capacity-1, once per view."""
    return torch.arange(capacity, device=device).repeat(views)
