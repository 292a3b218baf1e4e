"""The synthetic room: deterministic, exact depth and poses, handheld-like motion, fast enough to stream."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import torch

from ogmapping.datasets.synthetic import SyntheticSource, trajectory
from ogmapping.frames.camera import validate_pose
from ogmapping.frames.geometry import backproject, project


@pytest.fixture(scope="module")
def source() -> SyntheticSource:
    return SyntheticSource(n_frames=100, width=160, height=120, seed=3)


def test_same_seed_same_frames_other_seed_differs() -> None:
    a = SyntheticSource(n_frames=20, width=64, height=48, seed=7)[11]
    b = SyntheticSource(n_frames=20, width=64, height=48, seed=7)[11]
    c = SyntheticSource(n_frames=20, width=64, height=48, seed=8)[11]
    np.testing.assert_array_equal(a.rgb, b.rgb)
    np.testing.assert_array_equal(a.depth, b.depth)
    np.testing.assert_array_equal(a.c2w, b.c2w)
    assert not np.array_equal(a.c2w, c.c2w)


def test_frame_contents(source: SyntheticSource) -> None:
    frame = source[5]
    assert frame.index == 5 and frame.registered
    assert frame.rgb.shape == (120, 160, 3) and frame.rgb.dtype == np.float32
    assert frame.depth.shape == (120, 160) and frame.depth.dtype == np.float32
    assert float(frame.rgb.min()) >= 0.0 and float(frame.rgb.max()) <= 1.0
    assert frame.rgb.std() > 0.03  # textured, not flat
    assert np.all(frame.depth > 0.3) and np.all(frame.depth < 8.0)  # closed room: every pixel is valid
    validate_pose(frame.c2w)
    k = source.intrinsics
    assert math.degrees(2 * math.atan(k.width / 2 / k.fx)) == pytest.approx(65.0)
    assert (k.cx, k.cy) == (80.0, 60.0)


def inverse_depth_at(depth: np.ndarray, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Depth at sub-pixel positions by bilinear interpolation of 1/z (exact on planes), and where it is smooth."""
    x, y = uv[:, 0] - 0.5, uv[:, 1] - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    ok = (x0 >= 0) & (y0 >= 0) & (x0 + 1 < depth.shape[1]) & (y0 + 1 < depth.shape[0])
    x0, y0, fx, fy = x0[ok], y0[ok], (x - np.floor(x))[ok], (y - np.floor(y))[ok]
    corners = np.stack([depth[y0, x0], depth[y0, x0 + 1], depth[y0 + 1, x0], depth[y0 + 1, x0 + 1]])
    inv = 1.0 / corners
    value = (inv[0] * (1 - fx) + inv[1] * fx) * (1 - fy) + (inv[2] * (1 - fx) + inv[3] * fx) * fy
    smooth = corners.max(axis=0) - corners.min(axis=0) < 0.05
    result = np.zeros(len(uv))
    result[ok] = 1.0 / value
    mask = np.zeros(len(uv), bool)
    mask[ok] = smooth
    return result, mask


@pytest.mark.parametrize(("i", "j"), [(0, 4), (40, 47)])
def test_depth_and_poses_are_exact(source: SyntheticSource, i: int, j: int) -> None:
    a, b = source[i], source[j]
    k = source.intrinsics
    points = backproject(torch.from_numpy(a.depth).double(), k, torch.from_numpy(a.c2w))
    uv, z = project(points, k, torch.from_numpy(b.c2w))
    seen, smooth = inverse_depth_at(b.depth.astype(np.float64), uv.numpy())
    error = np.abs(seen - z.numpy())
    visible = smooth & (error < 0.05)  # the rest is occluded in frame j
    assert visible.sum() > 0.3 * len(points)
    assert float(np.median(error[visible])) < 1e-4  # float32 rounding only; half a pixel off gives ~2 mm


def test_motion_is_handheld_like_and_covers_the_room() -> None:
    poses = trajectory(100, seed=0)
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    relative = np.einsum("nji,njk->nik", poses[:-1, :3, :3], poses[1:, :3, :3])
    angles = np.degrees(np.arccos(np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert steps.mean() > 0.01 and steps.max() < 0.06
    assert angles.mean() > 1.0 and angles.max() < 4.0
    forward = poses[:, :3, 2]
    heading = np.unwrap(np.arctan2(forward[:, 1], forward[:, 0]))
    assert math.degrees(abs(heading[-1] - heading[0])) > 250  # with a 65 degree view: nearly all walls seen
    inside = (np.abs(poses[:, 0, 3]) < 2.5) & (np.abs(poses[:, 1, 3]) < 2.0) & (poses[:, 2, 3] > 0.5)
    assert inside.all()


def test_frame_time() -> None:
    source = SyntheticSource(n_frames=10, width=320, height=240)
    source[0]
    timings = []
    for position in range(1, 4):
        start = time.perf_counter()
        source[position]
        timings.append(time.perf_counter() - start)
    # About 30 ms on an idle core; the bound leaves room for a busy shared machine.
    assert min(timings) < 0.1
