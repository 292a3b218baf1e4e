"""Depth registration onto the colour grid and depth clipping in torch, at sizes the cameras fix.

The numpy path (``ogmapping.frames.preprocess``) selects the valid depth pixels and the footprint
candidates it keeps (``nonzero``) and scatters with ``np.minimum.at``; on a GPU each selection stops
the host until the device has caught up. Here every depth pixel takes part and whatever numpy drops
is written as +inf, which changes no nearest depth; the footprint candidates are a grid
of offsets around each projection as wide as the cameras allow, not as the data needs. No operator
waits for the device, so a frame's preparation queues behind nothing on the host.

The result equals numpy's bit for bit: the same float32 operations in the same order, divisions by
device tensors (CUDA divides by a Python number as a multiplication by its reciprocal), and the
footprint offsets in float64, as numpy promotes them.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.frame import Frame
from ogmapping.frames.preprocess import FOOTPRINT_CANDIDATES_PER_CHUNK, MAX_FOOTPRINT


def footprint_reach(depth_k: Intrinsics, color_k: Intrinsics, depth_to_color: np.ndarray | None) -> int:
    """How many colour pixels either side of its own a depth pixel may cover (0: only its own).

    numpy spreads footprints over offsets ``-ceil(widest / 2) - 1 ..`` when the widest footprint of
    the frame's depth pixels exceeds one pixel, and no candidate outside a footprint is kept, so any
    wider reach gives the same pixels. A footprint is the fx ratio times the depth ratio (depth
    camera's depth over colour camera's), capped at MAX_FOOTPRINT. The depth ratio is exactly 1
    without a transform or with one that keeps depth (third row 0 0 1 0: the colour camera beside
    the depth camera, as in 7-Scenes); otherwise it depends on the data, and the cap bounds it.
    """
    ratio = max(np.float32(color_k.fx / depth_k.fx), np.float32(color_k.fy / depth_k.fy))
    keeps_depth = depth_to_color is None or np.array_equal(
        np.asarray(depth_to_color, dtype=np.float32)[2], np.array([0, 0, 1, 0], dtype=np.float32))
    widest = min(float(ratio), MAX_FOOTPRINT) if keeps_depth else MAX_FOOTPRINT
    return 0 if widest <= 1.0 else math.ceil(widest / 2.0) + 1


def register_depth(depth: torch.Tensor, depth_k: Intrinsics, color_k: Intrinsics,
                   depth_to_color: np.ndarray | None = None) -> torch.Tensor:
    """``preprocess.reproject_depth`` on ``depth`` (Hd, Wd) where it lies: (H, W) float32, holes 0."""
    device = depth.device
    valid = (torch.isfinite(depth) & (depth > 0)).reshape(-1)
    z_depth = depth.to(torch.float32)
    grid_x = torch.arange(depth_k.width, dtype=torch.float32, device=device)
    grid_y = torch.arange(depth_k.height, dtype=torch.float32, device=device)[:, None]
    ray_x = (grid_x + 0.5 - depth_k.cx) / _constant(depth_k.fx, device)
    ray_y = (grid_y + 0.5 - depth_k.cy) / _constant(depth_k.fy, device)
    if depth_to_color is None:
        z, depth_ratio, keep = z_depth, torch.ones_like(z_depth), valid
        u = (color_k.fx * ray_x + color_k.cx).expand_as(z)
        v = (color_k.fy * ray_y + color_k.cy).expand_as(z)
    else:
        transform = np.asarray(depth_to_color, dtype=np.float32).tolist()
        x, y, z = ((row[0] * ray_x + row[1] * ray_y + row[2]) * z_depth + row[3] for row in transform[:3])
        keep = valid & (z > 1e-6).reshape(-1)
        u = color_k.fx * x / z + color_k.cx
        v = color_k.fy * y / z + color_k.cy
        depth_ratio = z_depth / z
    u, v, z = u.reshape(-1), v.reshape(-1), z.reshape(-1)
    width_u = torch.clamp_max(depth_ratio.reshape(-1) * float(np.float32(color_k.fx / depth_k.fx)), MAX_FOOTPRINT)
    width_v = torch.clamp_max(depth_ratio.reshape(-1) * float(np.float32(color_k.fy / depth_k.fy)), MAX_FOOTPRINT)
    pixels = color_k.width * color_k.height
    buffer = torch.full((pixels,), torch.inf, dtype=torch.float32, device=device)
    reach = footprint_reach(depth_k, color_k, depth_to_color)
    offsets = torch.arange(-reach, reach + 1, dtype=torch.float64, device=device)
    # numpy spreads footprints only when the widest one the frame keeps exceeds a pixel: a flag on the device.
    spread = torch.where(keep, torch.maximum(width_u, width_v), 0.0).amax() > 1.0 if reach else None
    chunk = max(1, FOOTPRINT_CANDIDATES_PER_CHUNK // len(offsets) ** 2)
    # What numpy drops is written too, as +inf (no minimum changes), at pixels spread over the image: written
    # to one spare slot, the device's atomic minima would all queue on its address.
    elsewhere = torch.arange(len(offsets) ** 2 * min(chunk, len(z)), device=device) % pixels
    for first in range(0, len(z), chunk):
        part = slice(first, first + chunk)
        cols, in_u = _covered(u[part], width_u[part], offsets, spread, color_k.width)
        rows, in_v = _covered(v[part], width_v[part], offsets, spread, color_k.height)
        writes = (in_v & keep[part])[:, None, :] & in_u[None, :, :]
        index = torch.where(writes, rows[:, None, :] * color_k.width + cols[None, :, :],
                            elsewhere[: writes.numel()].view(writes.shape))
        buffer.scatter_reduce_(0, index.reshape(-1), torch.where(writes, z[part], torch.inf).reshape(-1), "amin")
    return torch.where(torch.isinf(buffer), 0.0, buffer).reshape(color_k.height, color_k.width)


def _covered(position: torch.Tensor, width: torch.Tensor, offsets: torch.Tensor, spread: torch.Tensor | None,
             size: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Per offset and sample along one axis: the pixel (0 where unused) and whether the sample writes it,
    the pixel holding its projection or one whose centre its footprint covers, inside the image."""
    pixels = torch.floor(position).double() + offsets[:, None]
    covered = offsets[:, None] == 0
    if spread is not None:
        distance = (pixels + 0.5) - position.double()
        half = width / 2
        covered = covered | (spread & (distance >= -half) & (distance < half))
    covered = covered & (pixels >= 0) & (pixels < size)
    return torch.where(covered, pixels, 0.0).long(), covered


def clip_depth(depth: torch.Tensor, depth_min: float, depth_max: float) -> torch.Tensor:
    """``preprocess.clip_depth``: depth outside [depth_min, depth_max], and non-finite depth, set to 0."""
    return torch.where(~torch.isfinite(depth) | (depth < depth_min) | (depth > depth_max), 0.0, depth)


def prepare_depth(depth: torch.Tensor, frame: Frame, depth_min: float, depth_max: float) -> torch.Tensor:
    """``preprocess.prepare``'s depth for ``frame`` from its raw ``depth`` on any device: registered onto the
    colour grid (unless it lies there already), then clipped to the working range."""
    if not frame.registered:
        depth = register_depth(depth, frame.depth_intrinsics, frame.color_intrinsics, frame.depth_to_color)
    return clip_depth(depth, depth_min, depth_max)


def _constant(value: float, device: torch.device) -> torch.Tensor:
    """``value`` as a float32 scalar on ``device``, filled there (no copy from the host)."""
    return torch.full((), value, dtype=torch.float32, device=device)
