"""What a batched render takes: one set of Gaussians and one camera per view.

A mapping step renders its view and its window of keyframes, each view with its own decoded
Gaussians (the decoders are conditioned on the viewing direction). ``rasterize_batch`` takes them
together so a backend can render them in as few calls as it can (gsplat: one per image size).
"""

from __future__ import annotations

from collections.abc import Hashable, Iterable
from dataclasses import dataclass
from typing import Protocol

import torch

from ogmapping.render.rules import COVARIANCE_BLUR


class Splats(Protocol):
    """The Gaussians of one view, as ``rasterize`` takes them (see its docstring for shapes)."""

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor


@dataclass
class SplatSet:
    """Loose tensors as ``Splats``."""

    means: torch.Tensor
    quats: torch.Tensor
    scales: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor


@dataclass(frozen=True)
class Camera:
    """``viewmat`` (4, 4) world-to-camera and ``K`` (3, 3) pixel intrinsics of a ``width`` x ``height`` image;
    ``blur``, the variance in pixels^2 added to every splat's screen-space covariance (see ``rasterize``)."""

    viewmat: torch.Tensor
    K: torch.Tensor
    width: int
    height: int
    blur: float = COVARIANCE_BLUR

    @property
    def size(self) -> tuple[int, int]:
        return self.width, self.height


def parameters(splats: Splats) -> tuple[torch.Tensor, ...]:
    """(means, quats, scales, opacities, colors): the order every backend takes them in."""
    return splats.means, splats.quats, splats.scales, splats.opacities, splats.colors


def per_view(scenes: list[Splats] | Splats) -> list[Splats]:
    """A batch's scenes one per view: a list as it is, a stacked ``Splats`` (every tensor view first,
    (V, N, ...)) unbound into its views."""
    if isinstance(scenes, list | tuple):
        return list(scenes)
    return [SplatSet(*parts) for parts in zip(*(t.unbind(0) for t in parameters(scenes)), strict=True)]


def check_batch(scenes: list[Splats], cameras: list[Camera]) -> None:
    """One camera per scene, at least one view."""
    if len(scenes) != len(cameras):
        raise ValueError(f"rasterize_batch needs one camera per scene, got {len(scenes)} scenes and "
                         f"{len(cameras)} cameras")
    if not scenes:
        raise ValueError("rasterize_batch needs at least one view")


def grouped(keys: Iterable[Hashable]) -> list[list[int]]:
    """The positions of ``keys`` grouped by equal key, each group in order, the groups by first appearance: a
    batch's views split into the runs one kernel call takes (one image size, one blur)."""
    groups: dict[Hashable, list[int]] = {}
    for position, key in enumerate(keys):
        groups.setdefault(key, []).append(position)
    return list(groups.values())
