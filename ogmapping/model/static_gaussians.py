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

import functools
from dataclasses import dataclass

import torch

from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.geometry import world_to_camera
from ogmapping.model.decoders import Decoders, activate
from ogmapping.model.gaussians import FRUSTUM_MARGIN, GaussianSet, decoded_logits
from ogmapping.structure.anchor_colour import with_anchor_colours
from ogmapping.structure.anchors import AnchorMap


@dataclass
class DrawnGaussianSet(GaussianSet):
    """A view's Gaussians for every buffer row (G = capacity * n), with which of them are drawn."""

    drawn: torch.Tensor  # (G,) bool: live anchor in view and positive opacity
    in_view: torch.Tensor  # (capacity,) bool: live anchors in the view's frustum

    def drawn_count(self) -> torch.Tensor:  # type: ignore[override]
        """How many Gaussians the view draws, on the device (reading it makes the host wait)."""
        return self.drawn.sum()


@dataclass
class DrawnWindow:
    """Every view's Gaussians stacked, view first (V, G, ...): what the decode returns as one graph."""

    means: torch.Tensor  # (V, G, 3)
    quats: torch.Tensor  # (V, G, 4)
    scales: torch.Tensor  # (V, G, 3)
    opacities: torch.Tensor  # (V, G)
    colors: torch.Tensor  # (V, G, 3)
    drawn: torch.Tensor  # (V, G)
    anchor_opacity: torch.Tensor  # (V, capacity)
    in_view: torch.Tensor  # (V, capacity)
    rows: torch.Tensor  # (G,) buffer row of each Gaussian
    slots: torch.Tensor  # (G,)
    anchor_rows: torch.Tensor  # (capacity,) every buffer row

    def views(self) -> list[DrawnGaussianSet]:
        stacked = ("means", "quats", "scales", "opacities", "colors", "drawn", "anchor_opacity", "in_view")
        per_view = zip(*(getattr(self, name).unbind(0) for name in stacked), strict=True)
        return [DrawnGaussianSet(**dict(zip(stacked, parts, strict=True)), rows=self.rows, slots=self.slots,
                                 anchor_rows=self.anchor_rows) for parts in per_view]


@functools.lru_cache(maxsize=64)
def frustum_camera(intrinsics: Intrinsics, device: torch.device) -> torch.Tensor:
    """(7,) fx, fy, cx, cy and the frustum's pixel bounds (``FRUSTUM_MARGIN`` beyond the image: low, right,
    bottom) of ``intrinsics`` on ``device``, made once: shared, never modify it."""
    margin = FRUSTUM_MARGIN * max(intrinsics.width, intrinsics.height)
    values = [intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy, -margin, intrinsics.width + margin,
              intrinsics.height + margin]
    return torch.tensor(values, dtype=torch.float32, device=device)


def frustum_masks(anchors: AnchorMap, poses: torch.Tensor, cameras: torch.Tensor, far: float) -> torch.Tensor:
    """(V, capacity): the live anchors whose centres fall in each view's widened frustum (``in_frustum``),
    for camera-to-world ``poses`` (V, 4, 4) and ``cameras`` (V, 7) of ``frustum_camera``."""
    positions = anchors.buffer("positions")
    w2c = world_to_camera(poses.to(positions))
    camera = positions @ w2c[:, :3, :3].transpose(-1, -2) + w2c[:, None, :3, 3]  # (V, C, 3)
    z = camera[..., 2]
    safe_z = torch.where(z.abs() > 1e-9, z, torch.full_like(z, 1e-9))
    fx, fy, cx, cy, low, right, bottom = (value.unsqueeze(1) for value in cameras.unbind(1))
    u = fx * camera[..., 0] / safe_z + cx
    v = fy * camera[..., 1] / safe_z + cy
    inside = (z > 0.0) & (z < far) & (u >= low) & (u <= right) & (v >= low) & (v <= bottom)
    return inside & anchors.live


def decode_views(anchors: AnchorMap, features: torch.Tensor, decoders: Decoders, poses: torch.Tensor,
                 cameras: torch.Tensor, far: float, *, fused: bool = False) -> DrawnWindow:
    """The Gaussians of every buffer row as seen from each camera-to-world ``poses[i]`` with ``cameras[i]``
    (``frustum_camera``), those of anchors in its frustum (out to ``far``) drawn; ``fused`` as ``generate_drawn``."""
    return generate_drawn(anchors, features, decoders, poses[:, :3, 3], frustum_masks(anchors, poses, cameras, far),
                          fused=fused)


def generate_drawn(anchors: AnchorMap, features: torch.Tensor, decoders: Decoders, camera_centers: torch.Tensor,
                   in_view: torch.Tensor, *, fused: bool = False) -> DrawnWindow:
    """Each view's Gaussians of every buffer row, view i seen from ``camera_centers[i]`` (V, 3) with the
    anchors of ``in_view[i]`` (V, capacity) drawn; ``features`` holds every row's decoder features. The
    decoders run once over all (row, view) pairs: as torch operators, or with ``fused`` in the Triton
    kernels of ``triton_decode`` (the same values and gradients; CUDA, or CPU tensors when interpreted)."""
    capacity, n = anchors.capacity, anchors.n_offsets
    colours = anchors.parameter("colours") if anchors.with_colours else None
    if fused:
        from ogmapping.model.triton_decode import decode_window

        decoded = decode_window(features, anchors.buffer("positions"), anchors.parameter("offsets"),
                                anchors.parameter("log_scales"), colours, camera_centers, in_view, decoders)
    else:
        decoded = _torch_decode(anchors, features, decoders, camera_centers, in_view, colours)
    means, quats, scales, opacities, colors, drawn, anchor_opacity = decoded
    index = torch.arange(capacity * n, device=means.device)
    return DrawnWindow(means=means, quats=quats, scales=scales, opacities=opacities, colors=colors, drawn=drawn,
                       anchor_opacity=anchor_opacity, in_view=in_view, rows=index // n, slots=index % n,
                       anchor_rows=index[:capacity])


def _torch_decode(anchors: AnchorMap, features: torch.Tensor, decoders: Decoders, camera_centers: torch.Tensor,
                  in_view: torch.Tensor, colours: torch.Tensor | None) -> tuple[torch.Tensor, ...]:
    """``generate_drawn``'s values in torch operators: means, quats, scales, opacities, colours, drawn
    (V, capacity * n, ...) and each anchor's largest opacity (V, capacity)."""
    views, capacity = camera_centers.shape[0], anchors.capacity
    positions = anchors.buffer("positions")
    all_positions = positions.repeat(views, 1)
    centers = camera_centers.to(positions).unsqueeze(1).expand(views, capacity, 3).reshape(-1, 3)
    opacity, color, cov = decoded_logits(decoders, features.repeat(views, 1), all_positions, centers)
    if colours is not None:
        color = with_anchor_colours(color, colours, torch.arange(capacity, device=positions.device).repeat(views))
    n = anchors.n_offsets
    decoded = activate(opacity, color, cov, n)
    # repeated rather than gathered by rows (as gaussians.gaussian_values does): the same values, and the
    # compiled graph's rounding that tests/test_step_graphs.py holds equal to the eager one
    anchor_scale = torch.exp(anchors.parameter("log_scales")).repeat(views, 1)  # (V * C, 3)
    means = all_positions.unsqueeze(1) + anchors.parameter("offsets").repeat(views, 1, 1) * anchor_scale.unsqueeze(1)
    scales = anchor_scale.unsqueeze(1) * decoded.scale_factor
    drawn = (opacity > 0) & in_view.reshape(-1, 1)
    # where, not a product: a Gaussian not drawn passes no gradient back, as one left out would not
    opacities = torch.where(drawn, decoded.opacity, 0.0)
    per_view = capacity * n
    return (means.reshape(views, per_view, 3), decoded.quat.reshape(views, per_view, 4),
            scales.reshape(views, per_view, 3), opacities.reshape(views, per_view),
            decoded.color.reshape(views, per_view, 3), drawn.reshape(views, per_view),
            decoded.opacity.detach().amax(dim=1).view(views, capacity))
