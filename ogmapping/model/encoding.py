"""Anchor feature encodings: a multi-resolution hash grid (dense) or a feature per anchor (sparse)."""

from __future__ import annotations

import math

import torch
from torch import nn

from ogmapping.config import ModelConfig
from ogmapping.model.encoding_cpu import HashEncode
from ogmapping.model.row_gradients import RowGradients, SparseRowGather
from ogmapping.runtime.device_constants import on_device

# Large primes of the spatial hash (Teschner et al.), the first left at 1 as instant-NGP does.
HASH_PRIMES = (1, 2654435761, 805459861)
CORNERS = torch.tensor([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], dtype=torch.int64)


class HashGridEncoding(nn.Module):
    """Multi-resolution hash encoding in world coordinates, trilinearly interpolated.

    Resolutions are in cells per metre, so no scene bounds are needed in an online setting. The
    table's gradient is the rows a view read, kept in ``gradients``; ``optim.lazy_adam`` steps those only.
    """

    def __init__(self, config: ModelConfig, generator: torch.Generator | None = None) -> None:
        super().__init__()
        self.levels = config.hash_levels
        self.table_size = 2**config.hash_log2_size
        growth = (config.hash_max_resolution / config.hash_min_resolution) ** (1 / max(self.levels - 1, 1))
        resolutions = [config.hash_min_resolution * growth**level for level in range(self.levels)]
        self.register_buffer("resolutions", torch.tensor(resolutions, dtype=torch.float32), persistent=False)
        table = torch.empty(self.levels, self.table_size, config.hash_features_per_level)
        self.table = nn.Parameter(table.uniform_(-1e-4, 1e-4, generator=generator))
        self.gradients = RowGradients()  # the table's gradient rows, for ``optim.lazy_adam.LazyAdam``

    @property
    def output_dim(self) -> int:
        return self.levels * self.table.shape[-1]

    def forward(self, points: torch.Tensor, *, compiled: bool) -> torch.Tensor:
        """Features of world points (M, 3) -> (M, levels * features_per_level).

        ``compiled`` runs the Numba kernel of ``encoding_cpu`` (float32 on the CPU); both give the
        same rows and features (to float32 rounding) and the same sparse table gradient.
        """
        if compiled:
            return HashEncode.apply(points, self.table, self.resolutions, HASH_PRIMES, self.gradients)
        scaled = points.unsqueeze(1) * self.resolutions.view(1, -1, 1)  # (M, L, 3)
        base = torch.floor(scaled)
        fraction = scaled - base
        corners = base.to(torch.int64).unsqueeze(2) + on_device(CORNERS, points.device, torch.int64)  # (M, L, 8, 3)
        index = self._hash(corners)  # (M, L, 8)
        level_start = torch.arange(self.levels, device=points.device).view(1, -1, 1) * self.table_size
        rows = (index + level_start).reshape(-1)
        values = SparseRowGather.apply(self.table, rows, self.gradients).view(*index.shape, -1)  # (M, L, 8, F)
        corner_bits = on_device(CORNERS, points.device, points.dtype)
        weights = torch.where(
            corner_bits.view(1, 1, 8, 3) > 0, fraction.unsqueeze(2), 1.0 - fraction.unsqueeze(2)
        ).prod(-1)  # (M, L, 8)
        return (values * weights.unsqueeze(-1)).sum(2).flatten(1)

    def _hash(self, corners: torch.Tensor) -> torch.Tensor:
        hashed = corners[..., 0] * HASH_PRIMES[0]
        hashed = torch.bitwise_xor(hashed, corners[..., 1] * HASH_PRIMES[1])
        hashed = torch.bitwise_xor(hashed, corners[..., 2] * HASH_PRIMES[2])
        return torch.remainder(hashed, self.table_size)


def feature_dim(config: ModelConfig) -> int:
    """Width of the decoders' feature input for an encoding."""
    if config.encoding == "hash":
        return config.hash_levels * config.hash_features_per_level
    return config.feature_dim


def initial_anchor_features(count: int, dim: int, device: torch.device, generator: torch.Generator) -> torch.Tensor:
    """Small random per-anchor features, so the decoders see distinct inputs from the start.

    Drawn on the CPU from the session's generator: the same seed gives the same map on any device.
    """
    return (torch.randn(count, dim, generator=generator) / math.sqrt(dim)).to(device)
