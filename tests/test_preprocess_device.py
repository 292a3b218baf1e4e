"""Depth registration and clipping in torch (``frames.preprocess_device``) equal numpy's bit for bit, wait for
nothing on the host, and map as numpy's preparation does.

numpy's path (``frames.preprocess``) is the reference: random cameras (one camera, other intrinsics, a
baseline, a rotation, colour grids denser than the depth camera's, points behind the colour camera, depth
that is NaN, infinite, 0 or negative) and real 7-Scenes frames must register to the same float32 values.
"""

from __future__ import annotations

import dataclasses
import math
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load
from test_host_waits import HostWaits

from ogmapping.config import resolve
from ogmapping.datasets.sevenscenes import SevenScenes
from ogmapping.frames import preprocess
from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.frame import Frame
from ogmapping.frames.preprocess_device import footprint_reach, prepare_depth, register_depth
from ogmapping.frames.rotation import axis_angle_matrix
from ogmapping.mapper import Mapper
from ogmapping.quality.evaluation import open_frames

DEPTH_MIN, DEPTH_MAX = 0.1, 3.5


SEEDS = range(50)
SCALES = (0.6, 1.0, 2.0, 3.3, 9.0)  # colour pixels per depth pixel, about: 9 is over the footprint cap


def random_frame(seed: int) -> Frame:
    """Cameras and depth drawn from ``seed``; the seed picks the kind of camera pair (one camera, other
    intrinsics, a baseline along x, a small rotation, a large one that turns points behind) and the scale."""
    rng = np.random.default_rng(seed)
    width, height = (int(n) for n in rng.integers(6, 30, 2))
    depth_k = Intrinsics(float(rng.uniform(10, 40)), float(rng.uniform(10, 40)), float(rng.uniform(0, width)),
                         float(rng.uniform(0, height)), width, height)
    kind, scale = seed % 5, SCALES[seed // 5 % len(SCALES)]
    color_w, color_h = max(2, round(width * scale * rng.uniform(0.8, 1.2))), max(2, round(height * scale))
    color_k = depth_k if kind == 0 else Intrinsics(
        depth_k.fx * scale * float(rng.uniform(0.8, 1.2)), depth_k.fy * scale * float(rng.uniform(0.8, 1.2)),
        float(rng.uniform(0, color_w)), float(rng.uniform(0, color_h)), color_w, color_h)
    transform = None
    if kind >= 2:
        transform = np.eye(4)
        transform[0, 3] = rng.uniform(-0.1, 0.1)
        if kind >= 3:
            axis = rng.normal(size=3)
            angle = rng.uniform(0.0, 0.3) if kind == 3 else rng.uniform(1.5, 3.0)
            transform[:3, :3] = axis_angle_matrix(axis / np.linalg.norm(axis), angle)
            transform[:3, 3] = rng.uniform(-0.3, 0.3, 3)
    depth = rng.uniform(0.05, 4.0, (height, width)).astype(np.float32)
    odd = rng.random((height, width))
    for low, value in ((0.0, 0.0), (0.04, np.nan), (0.06, np.inf), (0.08, -1.0), (0.1, -np.inf), (0.11, 1e-7)):
        depth[(odd >= low) & (odd < low + 0.02)] = value
    return Frame(0, rng.random((color_h, color_w, 3), dtype=np.float32), depth, color_k, depth_k, np.eye(4),
                 depth_to_color=transform)


def widest_and_behind(frame: Frame) -> tuple[float, int]:
    """numpy's widest footprint for ``frame`` (in float64: to tell the cases apart, not to compare values) and
    how many valid depth pixels land behind the colour camera."""
    k = frame.depth_intrinsics
    rows, cols = np.nonzero(np.isfinite(frame.depth) & (frame.depth > 0))
    depth = frame.depth[rows, cols].astype(np.float64)
    if frame.depth_to_color is None:
        z, ahead = depth, np.ones(depth.shape, bool)
    else:
        x, y = (cols + 0.5 - k.cx) / k.fx * depth, (rows + 0.5 - k.cy) / k.fy * depth
        z = frame.depth_to_color[2] @ np.stack([x, y, depth, np.ones_like(depth)])
        ahead = z > 1e-6
    ratio = max(frame.color_intrinsics.fx / k.fx, frame.color_intrinsics.fy / k.fy)
    return float(np.minimum(ratio * depth[ahead] / z[ahead], 8.0).max(initial=0.0)), int((~ahead).sum())


def prepared_on_torch(frame: Frame, device: str | torch.device = "cpu") -> np.ndarray:
    return prepare_depth(torch.as_tensor(frame.depth, device=device), frame, DEPTH_MIN, DEPTH_MAX).cpu().numpy()


@pytest.mark.parametrize("seed", SEEDS)
def test_registration_equals_numpy_bit_for_bit(seed: int) -> None:
    frame = random_frame(seed)
    expected = preprocess.prepare(frame, DEPTH_MIN, DEPTH_MAX).depth
    got = prepared_on_torch(frame)
    assert got.dtype == expected.dtype and got.shape == expected.shape
    np.testing.assert_array_equal(got, expected)


def test_the_random_cameras_cover_every_way_numpy_registers() -> None:
    """Footprints spread (numpy's widest over a pixel) and not, a footprint grid wider than numpy's where the
    transform changes depth (spreading or not: the choice is made on the device), points behind the camera."""
    ways: Counter[str] = Counter()
    for seed in SEEDS:
        frame = random_frame(seed)
        widest, behind = widest_and_behind(frame)
        reach = footprint_reach(frame.depth_intrinsics, frame.color_intrinsics, frame.depth_to_color)
        ways["spread"] += widest > 1.0
        ways["spread, the grid wider than numpy's"] += widest > 1.0 and reach > math.ceil(widest / 2) + 1
        ways["not spread, on a grid"] += widest <= 1.0 and reach > 0
        ways["not spread"] += widest <= 1.0 and reach == 0
        ways["points behind"] += behind > 0
    assert len(ways) == 5 and min(ways.values()) >= 2, ways


def test_clipping_keeps_the_range_and_drops_the_rest_as_numpy_does() -> None:
    edges = [np.nextafter(np.float32(edge), np.float32(direction)) for edge in (DEPTH_MIN, DEPTH_MAX)
             for direction in (0, 10)]
    values = np.array([[DEPTH_MIN, DEPTH_MAX, *edges, 0.0, -0.0, np.nan, np.inf, -np.inf, 1.0]], np.float32)
    k = Intrinsics(10.0, 10.0, values.shape[1] / 2, 0.5, values.shape[1], 1)
    frame = Frame(0, np.zeros((1, values.shape[1], 3), np.float32), values, k, k, np.eye(4))
    np.testing.assert_array_equal(prepared_on_torch(frame), preprocess.prepare(frame, DEPTH_MIN, DEPTH_MAX).depth)


def test_registration_dispatches_no_operator_that_waits_for_the_device() -> None:
    """No ``nonzero``, boolean-mask index, ``item`` and the like; on the meta device (tensors without values)
    it runs whole, so nothing in it reads a value on the host or mixes in a tensor made there."""
    frame = random_frame(3)  # a rotation: footprints on a grid as wide as the cap
    assert footprint_reach(frame.depth_intrinsics, frame.color_intrinsics, frame.depth_to_color) > 0
    waits = HostWaits()
    with waits:
        prepared_on_torch(frame)
    assert not waits.sites, dict(waits.sites)
    meta = register_depth(torch.empty(frame.depth.shape, device="meta"), frame.depth_intrinsics,
                          frame.color_intrinsics, frame.depth_to_color)
    assert meta.shape == (frame.color_intrinsics.height, frame.color_intrinsics.width)


@pytest.mark.realdata
def test_real_frames_register_as_numpy_registers_them(seven_scenes: Path) -> None:
    """7-Scenes: depth camera beside the colour camera, other intrinsics; at full size and at half size."""
    source = SevenScenes(seven_scenes)
    for position in (0, 500):
        frame = source[position]
        for scaled in (frame, preprocess.resize_frame(frame, 0.5)):
            expected = preprocess.prepare(scaled, DEPTH_MIN, DEPTH_MAX).depth
            assert np.count_nonzero(expected) > 0.5 * expected.size
            np.testing.assert_array_equal(prepared_on_torch(scaled), expected)


OVERRIDES = {"keyframes.first_iterations": "2", "keyframes.iterations": "1", "poses.refine": "true"}


def mapped(seven_scenes: Path, on_device: bool) -> Mapper:
    frames = open_frames(str(seven_scenes), "7scenes", "0:6", scale=0.25)
    mapper = Mapper(resolve("sparse", overrides=OVERRIDES), "cpu")
    mapper.model.profile = dataclasses.replace(mapper.profile, device_frames=on_device)
    for position in frames.selection.streamed:
        prepared = mapper.prepare(frames.load(position))
        if on_device:  # the host's registered depth, read lazily, is numpy's
            assert prepared.host is None
            settings = mapper.config.octree
            reference = preprocess.prepare(prepared.given, settings.depth_min, settings.depth_max)
            np.testing.assert_array_equal(prepared.frame.depth, reference.depth)
            assert prepared.frame.depth_intrinsics == reference.depth_intrinsics and prepared.frame.registered
        mapper.process(prepared)
    return mapper


@pytest.mark.realdata
def test_a_map_from_frames_prepared_in_torch_is_the_numpy_prepared_map(seven_scenes: Path) -> None:
    numpy_map, torch_map = load(mapped(seven_scenes, False).snapshot()), load(mapped(seven_scenes, True).snapshot())
    assert numpy_map.keys() == torch_map.keys()
    for name, tensor in numpy_map.items():
        assert torch.equal(tensor, torch_map[name]), name
