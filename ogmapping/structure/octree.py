"""Sparse voxel octree over anchor levels, stored as one sorted Morton-code tensor per level.

Anchor level l has cells of size gamma_l = voxel_size / 4**l, so a level-l cell splits into 4x4x4
level-(l+1) cells (two octree depths per anchor level). Keeping each level's occupied codes sorted
makes membership a ``searchsorted`` and insertion a linear merge, so per-frame allocation costs
O(frame points + map size) with no sort or unique over the whole map. All work stays on the
tensors' device. ``insert_unread`` inserts without the host reading anything (the level's keys stay
padded with ``PAD`` until ``trim`` is told how many were new), so a frame's allocation and its
keyframe test share one read; ``insert`` reads the count at once.
"""

from __future__ import annotations

import numpy as np
import torch

from ogmapping.config import OctreeConfig
from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.geometry import in_frustum, project
from ogmapping.structure import morton

PAD = torch.iinfo(torch.int64).max  # no cell: sorts after every Morton code


class SparseVoxelOctree:
    """Occupied cells of every anchor level, as sorted unique int64 Morton codes."""

    def __init__(self, voxel_size: float, max_level: int, device: torch.device | str = "cpu") -> None:
        if voxel_size <= 0:
            raise ValueError(f"voxel_size must be positive, got {voxel_size}")
        if max_level < 0:
            raise ValueError(f"max_level must be >= 0, got {max_level}")
        self.voxel_size = float(voxel_size)
        self.max_level = int(max_level)
        self.device = torch.device(device)
        self._keys = [self._empty() for _ in range(self.levels)]
        self._unsettled: dict[int, int] = {}  # level -> its key count before an ``insert_unread``

    @classmethod
    def from_config(cls, config: OctreeConfig, device: torch.device | str = "cpu") -> SparseVoxelOctree:
        return cls(config.voxel_size, config.max_level, device)

    @property
    def levels(self) -> int:
        """Number of anchor levels (``max_level + 1``)."""
        return self.max_level + 1

    def cell_size(self, level: int) -> float:
        """gamma_l in metres."""
        self._check_level(level)
        return self.voxel_size / 4**level

    def keys(self, level: int = 0) -> torch.Tensor:
        """Sorted occupied codes of a level. Never modified in place, so safe to hold on to."""
        self._check_level(level)
        return self._keys[level]

    def count(self, level: int = 0) -> int:
        self._check_level(level)
        return int(self._keys[level].numel())

    def codes_of(self, points: torch.Tensor, level: int = 0, checked: bool = True) -> torch.Tensor:
        """Code (M,) of the level-``level`` cell holding each point, duplicates kept; ``checked=False`` for
        points known to be codable (``holds``), without the tests that make the host wait."""
        cell = self.cell_size(level)
        return morton.encode(morton.cell_coords(points, cell, checked), checked)

    def holds(self, points: torch.Tensor) -> torch.Tensor:
        """Which points (M, 3) every level can code: finite, and within the finest level's Morton range."""
        scaled = torch.floor(points / self.cell_size(self.max_level))
        return (torch.isfinite(scaled) & (scaled >= morton.COORD_MIN) & (scaled <= morton.COORD_MAX)).all(-1)

    def centers(self, codes: torch.Tensor, level: int = 0, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """World-space centres (M, 3) of cells, in metres (any codes decode: ``PAD``'s centre is meaningless)."""
        coords = morton.decode(codes, checked=False)
        return ((coords.to(torch.float64) + 0.5) * self.cell_size(level)).to(dtype)

    def centers_by_level(self, codes: torch.Tensor, levels: torch.Tensor) -> torch.Tensor:
        """World-space centres (M, 3) of cells whose levels differ per code (each level's centres of every
        code, kept where it is the code's level: no host wait)."""
        positions = torch.zeros(codes.numel(), 3, device=codes.device)
        for level in range(self.levels):
            positions = torch.where((levels == level).unsqueeze(-1), self.centers(codes, level), positions)
        return positions

    def contains(self, codes: torch.Tensor, level: int = 0) -> torch.Tensor:
        """Boolean mask: which codes are occupied at this level."""
        self._check_level(level)
        return _member(self._keys[level], codes.to(self.device, torch.int64))

    def insert(self, codes: torch.Tensor, level: int = 0) -> torch.Tensor:
        """Add cells; returns the sorted codes that were not occupied before."""
        self._check_level(level)
        candidates = torch.unique(codes.to(self.device, torch.int64))
        if candidates.numel() and bool((candidates < 0).any()):
            raise ValueError("Morton codes must be non-negative")
        new = candidates[~_member(self._keys[level], candidates)]
        if new.numel():
            self._keys[level] = _merge(self._keys[level], new)
        return new

    def insert_sorted(self, codes: torch.Tensor, level: int = 0) -> None:
        """Add cells known to be sorted, unique and unoccupied (growth's proposals), unchecked: no host wait."""
        self._check_level(level)
        self._keys[level] = _merge(self._keys[level], codes)

    def insert_unread(self, codes: torch.Tensor, level: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
        """``insert`` without the host reading anything: ``codes`` (any order, repeats, ``PAD`` for none)
        go into the level's keys, which end in ``PAD`` padding until ``trim``. Returns the new codes
        (sorted, then ``PAD``) and how many there are (a 0-dim tensor on the device)."""
        self._check_level(level)
        ordered = torch.sort(codes.to(self.device, torch.int64)).values
        first = torch.ones_like(ordered, dtype=torch.bool)
        first[1:] = ordered[1:] != ordered[:-1]
        new = first & (ordered != PAD) & ~_member(self._keys[level], ordered)
        # Each new code to its rank among the new ones, the others to a slot past the end, then cut off.
        slots = torch.where(new, torch.cumsum(new, 0) - 1, ordered.numel())
        fresh = torch.full((ordered.numel() + 1,), PAD, dtype=torch.int64, device=self.device)
        fresh.index_put_((slots,), ordered)
        fresh = fresh[: ordered.numel()]
        self._unsettled[level] = self._keys[level].numel()
        self._keys[level] = _merge(self._keys[level], fresh)
        return fresh, new.sum()

    def trim(self, level: int, added: int) -> None:
        """Drop the ``PAD`` padding ``insert_unread`` left on a level, now the host knows ``added``."""
        before = self._unsettled.pop(level, None)
        if before is not None:
            self._keys[level] = self._keys[level][: before + added]

    def remove(self, codes: torch.Tensor, level: int = 0) -> torch.Tensor:
        """Drop cells; returns the sorted codes that were occupied and are now gone."""
        self._check_level(level)
        doomed = torch.unique(codes.to(self.device, torch.int64))
        hit = _member(doomed, self._keys[level])
        removed = self._keys[level][hit]
        if removed.numel():
            self._keys[level] = self._keys[level][~hit]
        return removed

    def assign(self, codes: torch.Tensor, level: int = 0) -> None:
        """Replace a level's cells by ``codes``, already sorted and unique (unchecked: the naive
        unique allocation rebuilds level 0 this way each frame)."""
        self._check_level(level)
        self._keys[level] = codes.to(self.device, torch.int64)

    def allocate(self, points: torch.Tensor) -> torch.Tensor:
        """Occupy the coarsest cells touched by ``points``; returns the newly occupied codes."""
        return self.insert(self.codes_of(points.to(self.device), 0), 0)

    def observed(self, points: torch.Tensor) -> torch.Tensor:
        """Sorted unique coarsest codes touched by a point cloud (occupied or not)."""
        return torch.unique(self.codes_of(points.to(self.device), 0))

    def visible(
        self,
        intrinsics: Intrinsics,
        c2w: torch.Tensor | np.ndarray,
        level: int = 0,
        margin_px: float = 0.0,
        near: float = 0.05,
        far: float = 100.0,
    ) -> torch.Tensor:
        """Sorted occupied codes of a level whose cell centres project inside the camera frustum."""
        keys = self.keys(level)
        pose = torch.as_tensor(c2w, device=self.device)
        inside = in_frustum(self.centers(keys, level), intrinsics, pose, near=near, far=far, margin=margin_px)
        return keys[inside]

    def seen_mask(self, keys: torch.Tensor, depth: torch.Tensor, intrinsics: Intrinsics,
                  c2w: torch.Tensor) -> torch.Tensor:
        """Which of ``keys`` (coarsest codes; ``PAD`` never) a depth image sees: in its frustum and not behind
        its surface, as a mask (picking the codes out would make the host wait).

        Each cell is tested once, at its centre's pixel, so the set depends on the camera path and
        the voxel size but not on the image resolution or on how densely pixels sample the cells.
        A cell counts as seen where its centre lies no deeper than the measured surface plus two
        voxels (a centre below a surface seen at a grazing angle lies well behind it along the
        ray); pixels without a measurement see nothing.
        """
        if keys.numel() == 0:
            return torch.zeros_like(keys, dtype=torch.bool)
        uv, z = project(self.centers(keys, 0), intrinsics, c2w.to(self.device, torch.float32))
        column = torch.floor(uv[:, 0]).to(torch.int64)
        row = torch.floor(uv[:, 1]).to(torch.int64)
        inside = (z > 0) & (column >= 0) & (column < intrinsics.width) & (row >= 0) & (row < intrinsics.height)
        measured = depth[row.clamp(0, intrinsics.height - 1), column.clamp(0, intrinsics.width - 1)]
        return inside & (measured > 0) & (z <= measured + 2.0 * self.voxel_size) & (keys != PAD)

    def state_dict(self) -> dict[str, torch.Tensor]:
        """Plain tensors only, so the map can go into a safetensors file."""
        state = {
            "voxel_size": torch.tensor([self.voxel_size], dtype=torch.float64),
            "max_level": torch.tensor([self.max_level], dtype=torch.int64),
        }
        for level, keys in enumerate(self._keys):
            state[f"keys.{level}"] = keys.cpu()
        return state

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        """Replace this octree with a saved one, checking the keys since snapshots come from outside."""
        try:
            voxel_size = float(state["voxel_size"].reshape(-1)[0])
            max_level = int(state["max_level"].reshape(-1)[0])
            saved = [state[f"keys.{level}"] for level in range(max_level + 1)]
        except (KeyError, IndexError) as error:
            raise ValueError(f"octree state is incomplete: {error}") from error
        if not voxel_size > 0 or max_level < 0:
            raise ValueError("octree state has a non-positive voxel_size or negative max_level")
        for level, keys in enumerate(saved):
            if keys.dtype != torch.int64 or keys.ndim != 1:
                raise ValueError(f"octree keys.{level} must be a 1-D int64 tensor")
            if keys.numel() and (bool(keys[0] < 0) or not bool((keys[1:] > keys[:-1]).all())):
                raise ValueError(f"octree keys.{level} must be non-negative, sorted and unique")
        self.voxel_size = voxel_size
        self.max_level = max_level
        self._keys = [keys.to(self.device).clone() for keys in saved]

    def _check_level(self, level: int) -> None:
        if not 0 <= level <= self.max_level:
            raise ValueError(f"level must be in [0, {self.max_level}], got {level}")

    def _empty(self) -> torch.Tensor:
        return torch.empty(0, dtype=torch.int64, device=self.device)


def _member(sorted_keys: torch.Tensor, codes: torch.Tensor) -> torch.Tensor:
    """Which ``codes`` occur in ``sorted_keys`` (binary search, any order of ``codes``)."""
    if sorted_keys.numel() == 0:
        return torch.zeros(codes.shape, dtype=torch.bool, device=codes.device)
    index = torch.searchsorted(sorted_keys, codes).clamp_(max=sorted_keys.numel() - 1)
    return sorted_keys[index] == codes


def _merge(sorted_keys: torch.Tensor, sorted_new: torch.Tensor) -> torch.Tensor:
    """Linear merge of two sorted, disjoint code tensors (``sorted_new`` may end in ``PAD``s): each code's
    slot is its rank in the union, its index plus the other tensor's codes below it."""
    device = sorted_keys.device
    merged = torch.empty(sorted_keys.numel() + sorted_new.numel(), dtype=torch.int64, device=device)
    merged[torch.searchsorted(sorted_new, sorted_keys) + torch.arange(sorted_keys.numel(), device=device)] = sorted_keys
    merged[torch.searchsorted(sorted_keys, sorted_new) + torch.arange(sorted_new.numel(), device=device)] = sorted_new
    return merged
