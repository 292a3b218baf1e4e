"""Sparse voxel octree: allocation, membership and visibility against brute-force references."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from ogmapping.config import OctreeConfig
from ogmapping.frames.camera import Intrinsics
from ogmapping.structure import morton
from ogmapping.structure.octree import SparseVoxelOctree

VOXEL = 0.1


def brute_codes(points: torch.Tensor, size: float) -> set[int]:
    """Codes of touched cells, one point at a time with Python floor."""
    cells = {tuple(math.floor(c / size) for c in p) for p in points.tolist()}
    return {int(morton.encode(torch.tensor([cell]))) for cell in cells}


def random_cloud(generator: torch.Generator, count: int, centre: float) -> torch.Tensor:
    return (torch.rand(count, 3, generator=generator, dtype=torch.float64) - 0.5) * 2.0 + centre


def test_allocation_matches_set_difference() -> None:
    octree = SparseVoxelOctree(VOXEL, max_level=2)
    generator = torch.Generator().manual_seed(1)
    seen: set[int] = set()
    for step in range(8):
        points = random_cloud(generator, 400, centre=0.3 * step - 1.0)
        expected = brute_codes(points, VOXEL) - seen
        new = octree.allocate(points)
        assert new.tolist() == sorted(expected)
        seen |= expected
        keys = octree.keys(0)
        assert keys.tolist() == sorted(seen)
        assert octree.count(0) == len(seen)
    assert octree.allocate(points).numel() == 0
    assert octree.count(1) == octree.count(2) == 0


def test_observed_is_sorted_unique_cells() -> None:
    octree = SparseVoxelOctree(VOXEL, max_level=0)
    points = random_cloud(torch.Generator().manual_seed(2), 300, centre=0.0)
    assert octree.observed(points).tolist() == sorted(brute_codes(points, VOXEL))
    assert octree.count(0) == 0


def test_contains_insert_remove() -> None:
    octree = SparseVoxelOctree.from_config(OctreeConfig(voxel_size=VOXEL, max_level=1))
    codes = morton.encode(torch.tensor([[0, 0, 0], [-3, 5, 1], [7, -7, 2], [100, 0, -100]]))
    assert not bool(octree.contains(codes, 1).any())
    assert octree.insert(codes[[2, 0, 0, 1]], level=1).tolist() == sorted(codes[[0, 1, 2]].tolist())
    assert octree.contains(codes, 1).tolist() == [True, True, True, False]
    assert octree.count(0) == 0
    assert octree.insert(codes, level=1).tolist() == [int(codes[3])]
    removed = octree.remove(torch.cat([codes[[1, 1]], morton.encode(torch.tensor([[9, 9, 9]]))]), level=1)
    assert removed.tolist() == [int(codes[1])]
    assert octree.contains(codes, 1).tolist() == [True, False, True, True]
    assert octree.keys(1).tolist() == sorted(codes[[0, 2, 3]].tolist())
    with pytest.raises(ValueError, match="level"):
        octree.contains(codes, 2)


def test_centres_lie_inside_their_cells_at_every_level() -> None:
    octree = SparseVoxelOctree(VOXEL, max_level=2)
    points = random_cloud(torch.Generator().manual_seed(3), 500, centre=-0.2)
    for level in range(octree.levels):
        size = octree.cell_size(level)
        codes = torch.unique(octree.codes_of(points, level))
        centres = octree.centers(codes, level, dtype=torch.float64)
        assert torch.equal(octree.codes_of(centres, level), codes)
        lower = morton.decode(codes).to(torch.float64) * size
        assert torch.allclose(centres - lower, torch.full_like(centres, size / 2))
    # A level-l cell subdivides its level-(l-1) parent 4x per axis.
    fine = morton.cell_coords(points, octree.cell_size(2))
    assert torch.equal(torch.div(fine, 16, rounding_mode="floor"), morton.cell_coords(points, VOXEL))


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """OpenCV camera-to-world pose at ``eye`` looking at ``target``."""
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0.0, -1.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, down, forward], axis=1)
    pose[:3, 3] = eye
    return pose


@pytest.mark.parametrize("margin", [0.0, 8.0])
def test_visible_matches_per_cell_projection(margin: float) -> None:
    octree = SparseVoxelOctree(VOXEL, max_level=1)
    points = random_cloud(torch.Generator().manual_seed(4), 3000, centre=0.0) * 1.5
    octree.allocate(points)
    intrinsics = Intrinsics(fx=60.0, fy=55.0, cx=39.0, cy=31.0, width=80, height=60)
    pose = look_at(np.array([0.4, -0.3, -2.5]), np.array([0.2, 0.1, 0.0]))
    near, far = 0.05, 3.0
    w2c = np.linalg.inv(pose)
    expected = []
    for code, centre in zip(octree.keys(0).tolist(), octree.centers(octree.keys(0)).tolist(), strict=True):
        x, y, z = w2c[:3, :3] @ np.array(centre) + w2c[:3, 3]
        u, v = intrinsics.fx * x / z + intrinsics.cx, intrinsics.fy * y / z + intrinsics.cy
        if near < z < far and -margin <= u <= 80 + margin and -margin <= v <= 60 + margin:
            expected.append(code)
    visible = octree.visible(intrinsics, pose, margin_px=margin, near=near, far=far)
    assert 0 < len(expected) < octree.count(0)
    assert visible.tolist() == expected


def test_state_round_trip_and_validation() -> None:
    octree = SparseVoxelOctree(VOXEL, max_level=2)
    octree.allocate(random_cloud(torch.Generator().manual_seed(5), 200, centre=0.0))
    octree.insert(morton.encode(torch.tensor([[1, 2, 3], [-4, -5, -6]])), level=2)
    state = octree.state_dict()
    assert all(isinstance(value, torch.Tensor) for value in state.values())
    restored = SparseVoxelOctree(1.0, max_level=0)
    restored.load_state_dict(state)
    assert (restored.voxel_size, restored.max_level) == (VOXEL, 2)
    for level in range(3):
        assert torch.equal(restored.keys(level), octree.keys(level))
    unsorted = dict(state, **{"keys.0": state["keys.0"].flip(0)})
    with pytest.raises(ValueError, match="sorted"):
        restored.load_state_dict(unsorted)
    with pytest.raises(ValueError, match="incomplete"):
        restored.load_state_dict({k: v for k, v in state.items() if k != "keys.2"})


def seen_from(octree: SparseVoxelOctree, depth: torch.Tensor, intrinsics, c2w: torch.Tensor) -> torch.Tensor:
    """The occupied coarsest codes ``depth`` sees, picked out of the octree's keys by ``seen_mask``."""
    keys = octree.keys(0)
    return keys[octree.seen_mask(keys, depth, intrinsics, c2w)]


def test_seen_from_keeps_cells_in_front_of_the_surface_only() -> None:
    """A wall 2 m ahead: cells on it and before it are seen, cells well behind it and off-image are not."""
    octree = SparseVoxelOctree(0.1, 0)
    intrinsics = Intrinsics(50.0, 50.0, 32.0, 24.0, 64, 48)
    wall = torch.full((48, 64), 2.0)
    on_wall = torch.tensor([[0.0, 0.0, 2.0]])
    in_front = torch.tensor([[0.0, 0.0, 1.0]])
    behind = torch.tensor([[0.0, 0.0, 3.0]])
    outside = torch.tensor([[5.0, 0.0, 2.0]])
    for points in (on_wall, in_front, behind, outside):
        octree.allocate(points)
    seen = seen_from(octree, wall, intrinsics, torch.eye(4))
    expected = torch.cat([octree.codes_of(p) for p in (on_wall, in_front)]).sort().values
    assert torch.equal(seen, expected)
    assert seen_from(octree, torch.zeros(48, 64), intrinsics, torch.eye(4)).numel() == 0, "no depth, nothing seen"


def test_seen_from_does_not_depend_on_resolution() -> None:
    octree = SparseVoxelOctree(0.1, 0)
    generator = torch.Generator().manual_seed(0)
    points = torch.rand(2000, 3, generator=generator) * torch.tensor([4.0, 3.0, 1.0])
    octree.allocate(points - torch.tensor([2.0, 1.5, -1.5]))
    full = Intrinsics(80.0, 80.0, 40.0, 30.0, 80, 60)
    half = full.scaled(0.5)
    seen_full = seen_from(octree, torch.full((60, 80), 2.6), full, torch.eye(4))
    seen_half = seen_from(octree, torch.full((30, 40), 2.6), half, torch.eye(4))
    assert seen_full.numel() > 100 and torch.equal(seen_full, seen_half)
