"""Turn the anchors in view into the Gaussians of one view (only those with positive opacity)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.geometry import in_frustum
from ogmapping.model.decoders import DecodedAttributes, Decoders, activate
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

    def drawn_count(self) -> torch.Tensor | int:
        """How many Gaussians the view draws: all of them here (``static_gaussians`` marks some inert)."""
        return len(self)


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
    return _generate_one(anchors, features, decoders, camera_center, rows, compiled)


def generate_window(
    anchors: AnchorMap,
    features: Callable[[torch.Tensor], torch.Tensor],
    decoders: Decoders,
    camera_centers: list[torch.Tensor],
    rows: list[torch.Tensor],
    *,
    compiled: bool,
    shared_decode: bool,
) -> list[GaussianSet]:
    """The Gaussians of several views, view i's from the anchors ``rows[i]`` seen from
    ``camera_centers[i]``, each view assembled on its own (an anchor may be in several views).

    ``shared_decode`` runs the decoders once over every (anchor, view) pair of the window instead
    of once per view: a few large matmuls instead of many small ones, which is what a GPU wants.
    The results agree to float rounding (row sums of the decoders' weight gradients run in another
    order), so a map made either way is not bit for bit the other's.
    """
    if not shared_decode or len(rows) == 1:
        return [_generate_one(anchors, features, decoders, center, view_rows, compiled)
                for center, view_rows in zip(camera_centers, rows, strict=True)]
    counts = [int(view_rows.shape[0]) for view_rows in rows]
    all_rows = torch.cat(rows)
    positions = anchors.buffer("positions").index_select(0, all_rows)
    # Expanded views, not repeat_interleave: its repeats would be copied from the host to the device.
    per_row = torch.cat([center.to(positions).expand(count, 3) for center, count in zip(camera_centers, counts,
                                                                                         strict=True)])
    logits = _logits(anchors, decoders, features(all_rows), positions, per_row, all_rows)
    views = zip(rows, *(part.split(counts) for part in (positions, *logits)), strict=True)
    return [_assemble(anchors, view_rows, view_positions, *view_logits, compiled=compiled)
            for view_rows, view_positions, *view_logits in views]


def _generate_one(anchors: AnchorMap, features: Callable[[torch.Tensor], torch.Tensor], decoders: Decoders,
                  camera_center: torch.Tensor, rows: torch.Tensor, compiled: bool) -> GaussianSet:
    positions = anchors.buffer("positions").index_select(0, rows)
    logits = _logits(anchors, decoders, features(rows), positions, camera_center, rows)
    return _assemble(anchors, rows, positions, *logits, compiled=compiled)


def _logits(anchors: AnchorMap, decoders: Decoders, features: torch.Tensor, positions: torch.Tensor,
            camera_centers: torch.Tensor, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The decoders' logits, with each anchor's own colour added where the map keeps one."""
    opacity, color, cov = decoded_logits(decoders, features, positions, camera_centers)
    if anchors.with_colours:
        color = with_anchor_colours(color, anchors.parameter("colours"), rows)
    return opacity, color, cov


def _assemble(anchors: AnchorMap, rows: torch.Tensor, positions: torch.Tensor, opacity_logits: torch.Tensor,
              color_logits: torch.Tensor, cov: torch.Tensor, *, compiled: bool) -> GaussianSet:
    if compiled:
        return _assemble_compiled(anchors, rows, opacity_logits, color_logits, cov)
    return _assemble_torch(anchors, rows, positions, opacity_logits, color_logits, cov)


def gaussian_values(
    anchors: AnchorMap, rows: torch.Tensor, positions: torch.Tensor, opacity_logits: torch.Tensor,
    color_logits: torch.Tensor, cov: torch.Tensor,
) -> tuple[DecodedAttributes, torch.Tensor, torch.Tensor]:
    """The activated decoder outputs and the means and scales (R, n, 3) of the Gaussians of anchor ``rows``
    (R,) at ``positions`` (R, 3), before any of them is left out."""
    decoded = activate(opacity_logits, color_logits, cov, anchors.n_offsets)
    anchor_scale = torch.exp(anchors.parameter("log_scales")[rows])  # (R, 3)
    means = positions.unsqueeze(1) + anchors.parameter("offsets")[rows] * anchor_scale.unsqueeze(1)
    return decoded, means, anchor_scale.unsqueeze(1) * decoded.scale_factor


def _assemble_torch(anchors: AnchorMap, rows: torch.Tensor, positions: torch.Tensor, opacity_logits: torch.Tensor,
                    color_logits: torch.Tensor, cov: torch.Tensor) -> GaussianSet:
    """``positions``: the anchors' centres, ``anchors.positions[rows]``."""
    n = anchors.n_offsets
    decoded, means, scales = gaussian_values(anchors, rows, positions, opacity_logits, color_logits, cov)
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
        opacity_logits, color_logits, cov, anchors.buffer("positions"), anchors.parameter("log_scales"),
        anchors.parameter("offsets"), rows)
    return GaussianSet(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors,
                       rows=kept_rows, slots=slots, anchor_rows=rows, anchor_opacity=anchor_opacity)
