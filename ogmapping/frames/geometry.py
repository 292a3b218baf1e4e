"""Torch geometry on the conventions of ``ogmapping.frames.camera``: poses, pixel rays, projection, frustum tests."""

from __future__ import annotations

import functools

import torch

from ogmapping.frames.camera import Intrinsics


@functools.lru_cache(maxsize=64)
def intrinsics_matrix(
    intrinsics: Intrinsics, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32
) -> torch.Tensor:
    """The 3x3 pixel matrix K as a tensor, as the rasterizer takes it; shared, never modify it.

    Cached: on CUDA every new tensor is a host-to-device copy (a host synchronisation), and the
    mapper renders the same few intrinsics thousands of times.
    """
    return torch.as_tensor(intrinsics.matrix(), dtype=dtype, device=device)


def world_to_camera(c2w: torch.Tensor) -> torch.Tensor:
    """Invert a rigid camera-to-world transform without a general matrix inverse: [R^T, -R^T t; 0 0 0 1]
    (assembled by concatenation, a few operators however many poses are stacked)."""
    rotation, translation = c2w[..., :3, :].split((3, 1), dim=-1)
    inverse_rotation = rotation.transpose(-1, -2)
    top = torch.cat([inverse_rotation, -inverse_rotation @ translation], dim=-1)
    bottom = torch.zeros_like(top[..., :1, :])  # made on the device: a tensor of host values would be a copy to it
    bottom[..., 3] = 1.0
    return torch.cat([top, bottom], dim=-2)


def pixel_rays(intrinsics: Intrinsics, device: torch.device | str = "cpu") -> torch.Tensor:
    """Camera-space ray directions with z = 1 through every pixel centre, shape (H, W, 3)."""
    rows = torch.arange(intrinsics.height, device=device, dtype=torch.float32) + 0.5
    cols = torch.arange(intrinsics.width, device=device, dtype=torch.float32) + 0.5
    v, u = torch.meshgrid(rows, cols, indexing="ij")
    x = (u - intrinsics.cx) / intrinsics.fx
    y = (v - intrinsics.cy) / intrinsics.fy
    return torch.stack([x, y, torch.ones_like(x)], dim=-1)


def valid_depth(depth: torch.Tensor) -> torch.Tensor:
    """Pixels with a measured depth (finite and positive): the ones ``backproject`` returns, in order."""
    return torch.isfinite(depth) & (depth > 0)


def backproject(depth: torch.Tensor, intrinsics: Intrinsics, c2w: torch.Tensor) -> torch.Tensor:
    """World points of every valid depth pixel (``valid_depth``, row-major order), shape (M, 3)."""
    valid = valid_depth(depth)
    rays = pixel_rays(intrinsics, depth.device)[valid]
    points_camera = rays * depth[valid].unsqueeze(-1)
    return points_camera @ c2w[:3, :3].T.to(points_camera) + c2w[:3, 3].to(points_camera)


def grid_points(depth: torch.Tensor, intrinsics: Intrinsics, c2w: torch.Tensor,
                stride: int) -> tuple[torch.Tensor, torch.Tensor]:
    """World points (M, 3) of every ``stride``-th pixel per axis (from ``stride // 2``), row-major, and which
    have a valid depth: ``backproject``'s points of those pixels with the invalid ones kept in place, at a
    fixed size (dropping them would make the host wait for the device)."""
    start = stride // 2
    sampled = depth[start::stride, start::stride]
    rays = pixel_rays(intrinsics, depth.device)[start::stride, start::stride].reshape(-1, 3)
    valid = valid_depth(sampled).reshape(-1)
    points_camera = rays * torch.where(valid, sampled.reshape(-1), 0.0).unsqueeze(-1)
    return points_camera @ c2w[:3, :3].T.to(points_camera) + c2w[:3, 3].to(points_camera), valid


def project(points: torch.Tensor, intrinsics: Intrinsics, c2w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel coordinates (M, 2) and camera depth (M,) of world points."""
    w2c = world_to_camera(c2w.to(points))
    camera = points @ w2c[:3, :3].T + w2c[:3, 3]
    z = camera[:, 2]
    safe_z = torch.where(z.abs() > 1e-9, z, torch.full_like(z, 1e-9))
    u = intrinsics.fx * camera[:, 0] / safe_z + intrinsics.cx
    v = intrinsics.fy * camera[:, 1] / safe_z + intrinsics.cy
    return torch.stack([u, v], dim=-1), z


def in_frustum(
    points: torch.Tensor, intrinsics: Intrinsics, c2w: torch.Tensor, near: float = 0.05, far: float = 100.0,
    margin: float = 0.0,
) -> torch.Tensor:
    """Which world points project inside the image (grown by ``margin`` pixels) between near and far."""
    uv, z = project(points, intrinsics, c2w)
    return (
        (z > near)
        & (z < far)
        & (uv[:, 0] >= -margin)
        & (uv[:, 0] <= intrinsics.width + margin)
        & (uv[:, 1] >= -margin)
        & (uv[:, 1] <= intrinsics.height + margin)
    )
