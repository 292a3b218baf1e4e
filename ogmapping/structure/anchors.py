"""The anchor map: per-anchor rows in buffers with a capacity, grown and pruned with their optimiser state.

Each anchor v has a centre p_v (the centre of its octree cell, derived from its Morton code and
level so it is exact), a level l_v, a learnable log-scale s_v (3), n learnable offsets o_v (n, 3),
in the sparse version a learnable feature f_v and, with ``model.anchor_colour``, a learnable colour
c_v (3, in logits) added to the colour decoder's output for its n Gaussians. Gaussians sit at
p_v + s_v * o_v.
Per-Gaussian statistics for refinement and pruning live here too, and the moving average of the
learnable rows (``ogmapping.optim.averaging``), so that they follow the anchors whenever anchors are added
or removed.

Every row tensor is a buffer of ``capacity`` rows of which the first ``count`` are live: growth writes
rows into the buffers and pruning compacts them in place, so the tensors a step reads keep their shapes
(and their storage) between the rare capacity doublings, and a captured or compiled step stays valid.
Rows past the count are inert: zero values, zero optimiser moments, outside ``live``. The attributes
named after the rows (``anchors.offsets``) are views of the live rows; ``parameter(name)`` is the whole
learnable buffer, the tensor the optimiser steps.
"""

from __future__ import annotations

import torch
from torch import nn

LEARNABLE = ("log_scales", "offsets", "features", "colours")
INITIAL_CAPACITY = 1024
MOMENTS = ("exp_avg", "exp_avg_sq")


class LiveRows:
    """The live rows of one buffer of an ``AnchorMap``; assigning copies into them (same shape)."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __get__(self, anchors: AnchorMap | None, owner: type | None = None):
        if anchors is None:
            return self
        return anchors.buffer(self.name)[: anchors.count]

    def __set__(self, anchors: AnchorMap, value: torch.Tensor) -> None:
        rows = self.__get__(anchors)
        if value.shape != rows.shape:
            raise ValueError(f"anchors.{self.name}: shape {tuple(value.shape)}, expected {tuple(rows.shape)}")
        with torch.no_grad():
            rows.copy_(value)


class AnchorMap:
    """Anchors as rows of parallel buffers; learnable buffers are ``nn.Parameter``s."""

    codes = LiveRows()
    levels = LiveRows()
    positions = LiveRows()
    log_scales = LiveRows()
    offsets = LiveRows()
    features = LiveRows()
    colours = LiveRows()
    grad_sum = LiveRows()
    grad_count = LiveRows()
    spawned = LiveRows()
    max_opacity = LiveRows()
    observations = LiveRows()
    average_steps = LiveRows()

    def __init__(self, n_offsets: int, feature_dim: int, with_features: bool, device: torch.device,
                 with_colours: bool = False, capacity: int = INITIAL_CAPACITY) -> None:
        self.n_offsets = n_offsets
        self.feature_dim = feature_dim
        self.with_features = with_features
        self.with_colours = with_colours
        self.device = device
        self.count = 0
        self.capacity = capacity
        shapes = self._row_shapes()
        self.learnable = {name: nn.Parameter(self._inert(name, capacity)) for name in LEARNABLE}
        self.rows = {name: self._inert(name, capacity) for name in shapes if name not in LEARNABLE}
        # The moving average of each learnable row (how many steps each row has been averaged over is
        # the row buffer ``average_steps``).
        self.average_rows = {name: torch.zeros_like(self.learnable[name].detach()) for name in LEARNABLE}
        self.live = torch.zeros(capacity, dtype=torch.bool, device=device)

    def _row_shapes(self) -> dict[str, tuple[tuple[int, ...], torch.dtype, float]]:
        """Each buffer's row shape, dtype and inert value."""
        n, f32, i64 = self.n_offsets, torch.float32, torch.int64
        return {
            "codes": ((), i64, 0), "levels": ((), i64, 0), "positions": ((3,), f32, 0.0),
            "log_scales": ((3,), f32, 0.0), "offsets": ((n, 3), f32, 0.0),
            "features": ((self.feature_dim if self.with_features else 0,), f32, 0.0),
            "colours": ((3 if self.with_colours else 0,), f32, 0.0),
            "grad_sum": ((n,), f32, 0.0), "grad_count": ((n,), i64, 0), "spawned": ((n,), torch.bool, False),
            # Largest decoded opacity per anchor in this interval; -inf where it was not rendered at all.
            "max_opacity": ((), f32, -torch.inf), "observations": ((), i64, 0), "average_steps": ((), i64, 0),
        }

    def _inert(self, name: str, rows: int) -> torch.Tensor:
        shape, dtype, value = self._row_shapes()[name]
        return torch.full((rows, *shape), value, dtype=dtype, device=self.device)

    def __len__(self) -> int:
        return self.count

    def buffer(self, name: str) -> torch.Tensor:
        """The whole buffer (``capacity`` rows) of row tensor ``name``."""
        return self.learnable[name] if name in LEARNABLE else self.rows[name]

    def parameter(self, name: str) -> nn.Parameter:
        """The learnable buffer ``name``: what the optimiser steps and a step's gathers read."""
        return self.learnable[name]

    @property
    def averages(self) -> dict[str, torch.Tensor]:
        """The live rows of each learnable row's moving average."""
        return {name: average[: self.count] for name, average in self.average_rows.items()}

    def reset_statistics(self) -> None:
        """Zero the per-interval refinement statistics (``spawned`` persists: growth is once-only)."""
        for name in ("grad_sum", "grad_count", "max_opacity"):
            self.rows[name].fill_(self._row_shapes()[name][2])

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
        start, end = self.count, self.count + count
        self.reserve(end, optimizer)
        values = {
            "codes": codes, "levels": levels, "positions": positions.to(torch.float32),
            "log_scales": torch.log(cell_sizes.to(self.device)).unsqueeze(-1).expand(count, 3),
        }
        if features is not None:
            values["features"] = features
        if colours is not None and self.with_colours:
            values["colours"] = colours
        with torch.no_grad():
            for name in self._row_shapes():
                rows = self.buffer(name)[start:end]
                if name in values:
                    rows.copy_(values[name])
                else:
                    rows.fill_(self._row_shapes()[name][2])
            for average in self.average_rows.values():
                average[start:end] = 0
            for state in _moments(optimizer, self.learnable.values()):
                state[start:end] = 0
        self._set_count(end)

    def reserve(self, rows: int, optimizer: torch.optim.Optimizer | None) -> None:
        """Room for ``rows`` live rows: the buffers (and Adam's moments) grow to twice their capacity, or
        to ``rows`` if that is more, keeping every value; the optimiser is handed the new parameters."""
        if rows <= self.capacity:
            return
        capacity = max(rows, 2 * self.capacity)
        for name in self.rows:
            self.rows[name] = self._grown(self.rows[name], self._inert(name, capacity))
        self.average_rows = {name: self._grown(average, torch.zeros_like(self._inert(name, capacity)))
                             for name, average in self.average_rows.items()}
        for name in LEARNABLE:
            old = self.learnable[name]
            new = nn.Parameter(self._grown(old.detach(), self._inert(name, capacity)))
            _swap(optimizer, old, new, lambda state, rows=capacity: self._grown(
                state, state.new_zeros((rows, *state.shape[1:]))))
            self.learnable[name] = new
        self.capacity = capacity
        self.live = torch.zeros(capacity, dtype=torch.bool, device=self.device)
        self._set_count(self.count)

    def _grown(self, old: torch.Tensor, new: torch.Tensor) -> torch.Tensor:
        new[: self.count] = old[: self.count]
        return new

    def keep(self, mask: torch.Tensor, optimizer: torch.optim.Optimizer | None) -> None:
        """Keep only the live rows where ``mask`` is True (pruning), compacted in place in the buffers."""
        kept = torch.nonzero(mask).squeeze(-1)
        total = int(kept.numel())
        with torch.no_grad():
            buffers = [(self.buffer(name), self._row_shapes()[name][2]) for name in self._row_shapes()]
            buffers += [(average, 0) for average in self.average_rows.values()]
            buffers += [(state, 0) for state in _moments(optimizer, self.learnable.values())]
            for tensor, inert in buffers:
                tensor[:total] = tensor.index_select(0, kept)
                tensor[total: self.count] = inert
        self._set_count(total)

    def _set_count(self, count: int) -> None:
        self.count = count
        self.live.fill_(False)
        self.live[:count] = True

    def level_counts(self, max_level: int) -> list[int]:
        return [int((self.levels == level).sum()) for level in range(max_level + 1)]


def _moments(optimizer: torch.optim.Optimizer | None, params) -> list[torch.Tensor]:
    """Adam's row-shaped moments of ``params`` (none before its first step)."""
    if optimizer is None:
        return []
    return [optimizer.state[param][key] for param in params
            if param in optimizer.state for key in MOMENTS if key in optimizer.state[param]]


def _swap(optimizer: torch.optim.Optimizer | None, old: nn.Parameter, new: nn.Parameter, follow) -> None:
    """Hand ``optimizer`` parameter ``new`` in place of ``old``, carrying Adam's moments through ``follow``."""
    if optimizer is None:
        return
    for group in optimizer.param_groups:
        for index, param in enumerate(group["params"]):
            if param is old:
                group["params"][index] = new
                state = optimizer.state.pop(old, None)
                if state:
                    for key in MOMENTS:
                        state[key] = follow(state[key])
                    optimizer.state[new] = state


def cell_size(voxel_size: float, level: torch.Tensor | int) -> torch.Tensor | float:
    """gamma_l = gamma_0 / 4**l."""
    if isinstance(level, int):
        return voxel_size / 4**level
    return voxel_size / torch.pow(4.0, level.to(torch.float32))
