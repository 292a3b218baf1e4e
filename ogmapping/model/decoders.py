"""The three MLP decoders that turn an anchor's feature and viewing geometry into n Gaussians."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from ogmapping.runtime.device_constants import on_device

# Added to the decoded rotation so an untrained decoder yields valid, unrotated Gaussians.
IDENTITY_QUAT = torch.tensor([1.0, 0.0, 0.0, 0.0])


def _linear(in_dim: int, out_dim: int, generator: torch.Generator | None) -> nn.Linear:
    """nn.Linear's own initialisation, drawn from the session's generator, not torch's global one."""
    layer = nn.Linear(in_dim, out_dim)
    bound = 1.0 / math.sqrt(in_dim)
    with torch.no_grad():
        nn.init.kaiming_uniform_(layer.weight, a=math.sqrt(5), generator=generator)
        nn.init.uniform_(layer.bias, -bound, bound, generator=generator)
    return layer


def _mlp(in_dim: int, hidden: int, out_dim: int, generator: torch.Generator | None) -> nn.Sequential:
    return nn.Sequential(_linear(in_dim, hidden, generator), nn.ReLU(inplace=True),
                         _linear(hidden, out_dim, generator))


@dataclass
class DecodedAttributes:
    """Per anchor (V) and offset slot (n)."""

    opacity: torch.Tensor  # (V, n), tanh: Gaussians with opacity <= 0 are dropped for this view
    color: torch.Tensor  # (V, n, 3) in [0, 1]
    scale_factor: torch.Tensor  # (V, n, 3) in (0, 1), multiplies the anchor scale
    quat: torch.Tensor  # (V, n, 4) unnormalised (w, x, y, z)


class Decoders(nn.Module):
    """F_opacity, F_color and F_cov, each Linear(c + 4, hidden) -> ReLU -> Linear."""

    def __init__(self, feature_dim: int, n_offsets: int, hidden: int,
                 generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.n = n_offsets
        in_dim = feature_dim + 4
        self.opacity = _mlp(in_dim, hidden, n_offsets, generator)
        self.color = _mlp(in_dim, hidden, 3 * n_offsets, generator)
        self.cov = _mlp(in_dim, hidden, 7 * n_offsets, generator)

    def logits(self, features: torch.Tensor, view_dirs: torch.Tensor,
               distances: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The three MLPs' outputs before activation: opacity (V, n), colour (V, 3n), covariance (V, 7n)."""
        inputs = torch.cat([features, view_dirs, distances], dim=-1)
        return self.opacity(inputs), self.color(inputs), self.cov(inputs)

    def forward(self, features: torch.Tensor, view_dirs: torch.Tensor, distances: torch.Tensor) -> DecodedAttributes:
        return activate(*self.logits(features, view_dirs, distances), self.n)

    @torch.no_grad()
    def start_visible(self, opacity_logits: torch.Tensor, share: float) -> None:
        """Shift the opacity decoder's output bias per slot so that ``share`` of ``opacity_logits``
        (V, n), the first anchors' logits, turn positive (visible): the map then starts with that
        share of its Gaussians whatever the random start drew (config ``model.initial_visible``)."""
        self.opacity[-1].bias -= torch.quantile(opacity_logits, 1 - share, dim=0)


def _identity_quat(like: torch.Tensor) -> torch.Tensor:
    """(1, 0, 0, 0) on ``like``'s device: copied there once, or a graph's own constant when compiled."""
    if torch.compiler.is_compiling():
        return IDENTITY_QUAT.to(like)
    return on_device(IDENTITY_QUAT, like.device, like.dtype)


def activate(opacity: torch.Tensor, color: torch.Tensor, cov: torch.Tensor, n: int) -> DecodedAttributes:
    """tanh opacity, sigmoid colour and scale factor, identity-offset quaternion."""
    count = opacity.shape[0]
    cov = cov.view(count, n, 7)
    return DecodedAttributes(
        opacity=torch.tanh(opacity),
        color=torch.sigmoid(color.view(count, n, 3)),
        scale_factor=torch.sigmoid(cov[..., :3]),
        quat=cov[..., 3:] + _identity_quat(cov),
    )
