"""The anchor map: per-anchor tensors, grown and pruned with their optimiser state.

Each anchor v has a centre p_v (the centre of its octree cell, derived from its Morton code and
level so it is exact), a level l_v, a learnable log-scale s_v (3), n learnable offsets o_v (n, 3),
in the sparse version a learnable feature f_v and, with ``model.anchor_colour``, a learnable colour
c_v (3, in logits) added to the colour decoder's output for its n Gaussians. Gaussians sit at
p_v + s_v * o_v.
Per-Gaussian statistics for refinement and pruning live here too, and the moving average of the
learnable rows (``ogmapping.optim.averaging``), so that they follow the anchors whenever anchors are added
or removed.
"""

from __future__ import annotations

import torch
from torch import nn

LEARNABLE = ("log_scales", "offsets", "features", "colours")


class AnchorMap(nn.Module):
    """Anchors as rows of parallel tensors; learnable rows are ``nn.Parameter``s."""

    def __init__(self, n_offsets: int, feature_dim: int, with_features: bool, device: torch.device,
                 with_colours: bool = False) -> None:
        super().__init__()
        self.n_offsets = n_offsets
        self.feature_dim = feature_dim
        self.with_features = with_features
        self.with_colours = with_colours
        self.device = device
        self.codes = torch.zeros(0, dtype=torch.int64, device=device)
        self.levels = torch.zeros(0, dtype=torch.int64, device=device)
        self.positions = torch.zeros(0, 3, device=device)
        self.log_scales = nn.Parameter(torch.zeros(0, 3, device=device))
        self.offsets = nn.Parameter(torch.zeros(0, n_offsets, 3, device=device))
        self.features = nn.Parameter(torch.zeros(0, feature_dim if with_features else 0, device=device))
        self.colours = nn.Parameter(torch.zeros(0, 3 if with_colours else 0, device=device))
        self.reset_statistics()
        self.spawned = torch.zeros(0, n_offsets, dtype=torch.bool, device=device)
        self.observations = torch.zeros(0, dtype=torch.int64, device=device)
        # The moving average of each learnable row, and how many steps each row has been averaged over.
        self.averages = {name: torch.zeros_like(getattr(self, name).detach()) for name in LEARNABLE}
        self.average_steps = torch.zeros(0, dtype=torch.int64, device=device)

    def __len__(self) -> int:
        return int(self.positions.shape[0])

    def reset_statistics(self) -> None:
        """Zero the per-interval refinement statistics (``spawned`` persists: growth is once-only)."""
        self.grad_sum = torch.zeros(len(self), self.n_offsets, device=self.device)
        self.grad_count = torch.zeros(len(self), self.n_offsets, dtype=torch.int64, device=self.device)
        # Largest decoded opacity per anchor in this interval; -inf where it was not rendered at all.
        self.max_opacity = torch.full((len(self),), -torch.inf, device=self.device)

    def add(
        self,
        codes: torch.Tensor,
        levels: torch.Tensor,
        positions: torch.Tensor,
        cell_sizes: torch.Tensor,
        features: torch.Tensor | None,
        optimizer: torch.optim.Optimizer | None,
        colours: torch.Tensor | None = None,
    ) -> None:
        """Append anchors; new rows start with scale = cell size and zero offsets (and, without
        ``colours``, a zero colour logit: the decoder's colour alone)."""
        count = int(codes.shape[0])
        if count == 0:
            return
        device = self.device
        new_values = {
            "log_scales": torch.log(cell_sizes.to(device)).unsqueeze(-1).expand(count, 3).contiguous(),
            "offsets": torch.zeros(count, self.n_offsets, 3, device=device),
            "features": (
                features.to(device)
                if features is not None
                else torch.zeros(count, self.features.shape[1], device=device)
            ),
            "colours": (
                colours.to(device)
                if colours is not None and self.with_colours
                else torch.zeros(count, self.colours.shape[1], device=device)
            ),
        }
        for name in LEARNABLE:
            self._replace(name, torch.cat([getattr(self, name).detach(), new_values[name]]), optimizer,
                          lambda state, n=count: torch.cat([state, state.new_zeros((n, *state.shape[1:]))]))
        self.codes = torch.cat([self.codes, codes.to(device)])
        self.levels = torch.cat([self.levels, levels.to(device)])
        self.positions = torch.cat([self.positions, positions.to(device, torch.float32)])
        shape = (count, self.n_offsets)
        self.grad_sum = torch.cat([self.grad_sum, torch.zeros(shape, device=device)])
        self.grad_count = torch.cat([self.grad_count, torch.zeros(shape, dtype=torch.int64, device=device)])
        self.spawned = torch.cat([self.spawned, torch.zeros(shape, dtype=torch.bool, device=device)])
        self.max_opacity = torch.cat([self.max_opacity, torch.full((count,), -torch.inf, device=device)])
        self.observations = torch.cat([self.observations, torch.zeros(count, dtype=torch.int64, device=device)])
        for name in LEARNABLE:
            self.averages[name] = torch.cat([self.averages[name], torch.zeros_like(new_values[name])])
        self.average_steps = torch.cat([self.average_steps, torch.zeros(count, dtype=torch.int64, device=device)])

    def keep(self, mask: torch.Tensor, optimizer: torch.optim.Optimizer | None) -> None:
        """Keep only the rows where ``mask`` is True (pruning)."""
        for name in LEARNABLE:
            self._replace(name, getattr(self, name).detach()[mask], optimizer, lambda state: state[mask])
        for name in ("codes", "levels", "positions", "grad_sum", "grad_count", "spawned", "max_opacity",
                     "observations", "average_steps"):
            setattr(self, name, getattr(self, name)[mask])
        self.averages = {name: average[mask] for name, average in self.averages.items()}

    def _replace(self, name: str, value: torch.Tensor, optimizer: torch.optim.Optimizer | None, follow) -> None:
        """Swap a learnable tensor for ``value``, carrying Adam's moments through ``follow``."""
        old = getattr(self, name)
        new = nn.Parameter(value.contiguous())
        if optimizer is not None:
            for group in optimizer.param_groups:
                for index, param in enumerate(group["params"]):
                    if param is old:
                        group["params"][index] = new
                        state = optimizer.state.pop(old, None)
                        if state:
                            for key in ("exp_avg", "exp_avg_sq"):
                                state[key] = follow(state[key])
                            optimizer.state[new] = state
        setattr(self, name, new)

    def level_counts(self, max_level: int) -> list[int]:
        return [int((self.levels == level).sum()) for level in range(max_level + 1)]


def cell_size(voxel_size: float, level: torch.Tensor | int) -> torch.Tensor | float:
    """gamma_l = gamma_0 / 4**l."""
    if isinstance(level, int):
        return voxel_size / 4**level
    return voxel_size / torch.pow(4.0, level.to(torch.float32))
