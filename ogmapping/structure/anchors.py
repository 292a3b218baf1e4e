"""The anchor map: per-anchor rows in buffers with a capacity, grown and pruned with their optimiser state.

Each anchor v has a centre p_v (the centre of its octree cell, derived from its Morton code and
level so it is exact), a level l_v, a learnable log-scale s_v (3), n learnable offsets o_v (n, 3),
in the sparse version a learnable feature f_v and, with ``model.anchor_colour``, a learnable colour
c_v (3, in logits) added to the colour decoder's output for its n Gaussians. Gaussians sit at
p_v + s_v * o_v.
Per-Gaussian statistics for refinement and pruning live here too, and the moving average of the
learnable rows (``ogmapping.optim.averaging``), so that they follow the anchors whenever anchors are added
or removed.

Each anchor also remembers the keyframe it belongs to (``keyframe``, the keyframe's position in the
mapper's keyframe list), so a pose correction of that keyframe moves it (``ogmapping.mapping.corrections``):
anchors a frame allocates belong to that frame if it becomes a keyframe, else to the newest keyframe
before it (a frame that is not a keyframe overlaps that one's view by at least the insertion threshold,
so its pose is the nearest one the map keeps); anchors grown by refinement inherit their parent's;
-1 where there is no keyframe (the very first frame's anchors before it is inserted, maps loaded from
snapshots written before anchors kept it).

Every row tensor is a buffer of ``capacity`` rows of which the first ``count`` are live: growth writes
rows into the buffers and pruning compacts them in place, so the tensors a step reads keep their shapes
(and their storage) between the rare capacity doublings, and a captured or compiled step stays valid.
Rows past the count are inert: zero values, zero optimiser moments, outside ``live``. The attributes
named after the rows (``anchors.offsets``) are views of the live rows; ``parameter(name)`` is the whole
learnable buffer, the tensor the optimiser steps.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn

LEARNABLE = ("log_scales", "offsets", "features", "colours")
# Every row buffer, learnable or not.
ROWS = ("codes", "levels", "positions", *LEARNABLE, "grad_sum", "grad_count", "spawned", "max_opacity", "observations",
        "average_steps", "keyframe")
INITIAL_CAPACITY = 1024
MOMENTS = ("exp_avg", "exp_avg_sq")


class RowSpec(NamedTuple):
    """One row buffer's row shape, dtype and the value of its inert rows."""

    shape: tuple[int, ...]
    dtype: torch.dtype
    inert: float | bool


class LiveRows:
    """The live rows of one buffer of an ``AnchorMap``; assigning copies into them (same shape)."""

    def __init__(self, name: str) -> None:
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
    """Anchors as rows of parallel buffers; learnable buffers are ``nn.Parameter``s. Each name of ``ROWS``
    is an attribute (``anchors.offsets``): the live rows of its buffer, ``LiveRows``."""

    def __init__(self, n_offsets: int, feature_dim: int, with_features: bool, device: torch.device,
                 with_colours: bool = False, capacity: int = INITIAL_CAPACITY) -> None:
        self.n_offsets = n_offsets
        self.feature_dim = feature_dim
        self.with_features = with_features
        self.with_colours = with_colours
        self.device = device
        self.count = 0
        self.capacity = capacity
        self.specs = self._row_specs()
        self.learnable = {name: nn.Parameter(self._inert(name, capacity)) for name in LEARNABLE}
        self.rows = {name: self._inert(name, capacity) for name in ROWS if name not in LEARNABLE}
        # The moving average of each learnable row (how many steps each row has been averaged over is
        # the row buffer ``average_steps``).
        self.average_rows = {name: torch.zeros_like(self.learnable[name].detach()) for name in LEARNABLE}
        self.live = torch.zeros(capacity, dtype=torch.bool, device=device)

    def _row_specs(self) -> dict[str, RowSpec]:
        """Each buffer's ``RowSpec``, by the names of ``ROWS``."""
        n, f32, i64 = self.n_offsets, torch.float32, torch.int64
        specs = {
            "codes": RowSpec((), i64, 0), "levels": RowSpec((), i64, 0), "positions": RowSpec((3,), f32, 0.0),
            "log_scales": RowSpec((3,), f32, 0.0), "offsets": RowSpec((n, 3), f32, 0.0),
            "features": RowSpec((self.feature_dim if self.with_features else 0,), f32, 0.0),
            "colours": RowSpec((3 if self.with_colours else 0,), f32, 0.0),
            "grad_sum": RowSpec((n,), f32, 0.0), "grad_count": RowSpec((n,), i64, 0),
            "spawned": RowSpec((n,), torch.bool, False),
            # Largest decoded opacity per anchor in this interval; -inf where it was not rendered at all.
            "max_opacity": RowSpec((), f32, -torch.inf), "observations": RowSpec((), i64, 0),
            "average_steps": RowSpec((), i64, 0),
            "keyframe": RowSpec((), i64, -1),  # the keyframe the anchor belongs to; -1: none
        }
        return {name: specs[name] for name in ROWS}

    def _inert(self, name: str, rows: int) -> torch.Tensor:
        spec = self.specs[name]
        return torch.full((rows, *spec.shape), spec.inert, dtype=spec.dtype, device=self.device)

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
            self.rows[name].fill_(self.specs[name].inert)

    def add(
        self,
        codes: torch.Tensor,
        levels: torch.Tensor,
        positions: torch.Tensor,
        cell_sizes: torch.Tensor,
        features: torch.Tensor | None,
        optimizer: torch.optim.Optimizer | None,
        colours: torch.Tensor | None = None,
        keyframes: torch.Tensor | int = -1,
    ) -> None:
        """Append anchors; new rows start with scale = cell size and zero offsets (and, without
        ``colours``, a zero colour logit: the decoder's colour alone); ``keyframes``: the keyframe each
        belongs to (one for all, or one per row)."""
        count = int(codes.shape[0])
        if count == 0:
            return
        start, end = self.count, self.count + count
        self.reserve(end, optimizer)
        values = {
            "codes": codes, "levels": levels, "positions": positions.to(torch.float32),
            "log_scales": torch.log(cell_sizes.to(self.device)).unsqueeze(-1).expand(count, 3),
            "keyframe": torch.as_tensor(keyframes, dtype=torch.int64, device=self.device).expand(count),
        }
        if features is not None:
            values["features"] = features
        if colours is not None and self.with_colours:
            values["colours"] = colours
        with torch.no_grad():
            for name, spec in self.specs.items():
                rows = self.buffer(name)[start:end]
                if name in values:
                    rows.copy_(values[name])
                else:
                    rows.fill_(spec.inert)
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

    def keep(self, mask: torch.Tensor, optimizer: torch.optim.Optimizer | None, total: int) -> None:
        """Keep only the live rows where ``mask`` is True (pruning), compacted in place in the buffers;
        ``total`` is how many are (read by the caller with other values: counting here would wait)."""
        kept = torch.nonzero_static(mask, size=total).squeeze(-1)
        with torch.no_grad():
            buffers = [(self.buffer(name), spec.inert) for name, spec in self.specs.items()]
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


for _name in ROWS:
    setattr(AnchorMap, _name, LiveRows(_name))


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
