"""Frame preprocessing before mapping: resizing, depth registration onto the colour grid, depth clipping.

The mapper supervises colour and depth at the same pixels, so depth from a separate camera is
re-projected into the colour camera first. All of it is vectorised numpy.
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.frame import Frame

# Registration spreads one depth pixel over at most this many colour pixels per axis: colour
# cameras sampling more than 8x as densely as their depth camera are refused by the server, and a
# point almost touching the colour camera (its footprint grows as the depth ratio) is capped.
MAX_FOOTPRINT = 8.0
FOOTPRINT_CANDIDATES_PER_CHUNK = 1 << 22  # (colour pixel, depth pixel) pairs tested at once: tens of MB of temporaries


def _nearest_indices(source: int, target: int) -> np.ndarray:
    """Source index whose pixel contains each target pixel centre (pixel centres at +0.5)."""
    centres = (np.arange(target) + 0.5) * (source / target)
    return np.minimum(np.floor(centres).astype(np.int64), source - 1)


def resize_depth(depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """Nearest-neighbour resize: every output value is a measured one, none blended across edges."""
    rows = _nearest_indices(depth.shape[0], height)
    cols = _nearest_indices(depth.shape[1], width)
    return depth[rows[:, None], cols[None, :]]


def resize_frame(frame: Frame, scale: float) -> Frame:
    """The frame with colour and depth images resized by ``scale`` and intrinsics to match."""
    if scale <= 0:
        raise ValueError(f"scale must be positive (got {scale})")
    if scale == 1.0:
        return frame
    color_k = frame.color_intrinsics.scaled(scale)
    depth_k = color_k if frame.depth_intrinsics == frame.color_intrinsics else frame.depth_intrinsics.scaled(scale)
    interpolation = cv2.INTER_AREA if scale < 1.0 else cv2.INTER_LINEAR
    rgb = cv2.resize(frame.rgb, (color_k.width, color_k.height), interpolation=interpolation)
    return dataclasses.replace(
        frame,
        rgb=np.clip(rgb, 0.0, 1.0).astype(np.float32, copy=False),
        depth=resize_depth(frame.depth, depth_k.width, depth_k.height),
        color_intrinsics=color_k,
        depth_intrinsics=depth_k,
    )


def clip_depth(frame: Frame, depth_min: float, depth_max: float) -> Frame:
    """The frame with depth outside [depth_min, depth_max] (and non-finite depth) marked invalid (0)."""
    depth = frame.depth.copy()
    depth[~np.isfinite(depth) | (depth < depth_min) | (depth > depth_max)] = 0.0
    return dataclasses.replace(frame, depth=depth)


def reproject_depth(
    depth: np.ndarray,
    depth_k: Intrinsics,
    color_k: Intrinsics,
    depth_to_color: np.ndarray | None = None,
) -> np.ndarray:
    """Depth seen from the colour camera, on its pixel grid, nearest surface kept, holes 0.

    Each valid depth pixel is back-projected through its centre, moved into the colour camera and
    written to the colour pixel containing its projection. Where the colour camera samples more
    densely than the depth camera (e.g. ScanNet's 1296x968 colour over 640x480 depth) a depth pixel
    also covers every colour pixel whose centre lies inside its projected footprint, so upsampling
    leaves no regular pattern of holes.
    """
    valid = np.isfinite(depth) & (depth > 0)
    rows, cols = np.nonzero(valid)
    z_depth = depth[rows, cols].astype(np.float32)
    ray_x = ((np.arange(depth_k.width, dtype=np.float32) + 0.5 - depth_k.cx) / depth_k.fx)[cols]
    ray_y = ((np.arange(depth_k.height, dtype=np.float32) + 0.5 - depth_k.cy) / depth_k.fy)[rows]
    if depth_to_color is None:
        # Same optical centre and axes: the pixel's ray direction alone fixes where it lands.
        z, depth_ratio = z_depth, np.ones_like(z_depth)
        u = color_k.fx * ray_x + color_k.cx
        v = color_k.fy * ray_y + color_k.cy
    else:
        transform = np.asarray(depth_to_color, dtype=np.float32)
        x, y, z = (
            (transform[i, 0] * ray_x + transform[i, 1] * ray_y + transform[i, 2]) * z_depth + transform[i, 3]
            for i in range(3)
        )
        ahead = z > 1e-6
        x, y, z, z_depth = x[ahead], y[ahead], z[ahead], z_depth[ahead]
        u = color_k.fx * x / z + color_k.cx
        v = color_k.fy * y / z + color_k.cy
        depth_ratio = z_depth / z

    # Footprint of one depth pixel in colour pixels: its metric size at its depth, seen from the colour camera,
    # capped so that the candidates per depth pixel, and with them the work, stay bounded.
    width_u = np.minimum(np.float32(color_k.fx / depth_k.fx) * depth_ratio, np.float32(MAX_FOOTPRINT))
    width_v = np.minimum(np.float32(color_k.fy / depth_k.fy) * depth_ratio, np.float32(MAX_FOOTPRINT))
    buffer = np.full(color_k.width * color_k.height, np.inf, dtype=np.float32)
    widest = max(np.max(width_u, initial=0.0), np.max(width_v, initial=0.0))
    if widest <= 1.0:
        _splat(buffer, color_k, np.floor(u), np.floor(v), z)
    else:
        # Candidate colour pixels near each projection; keep the containing one and those whose
        # centre falls inside the footprint. Depth pixels go in chunks: peak memory stays the same
        # for any image size.
        offsets = np.arange(-int(np.ceil(widest / 2.0)) - 1, int(np.ceil(widest / 2.0)) + 2)
        chunk = max(1, FOOTPRINT_CANDIDATES_PER_CHUNK // len(offsets) ** 2)
        for first in range(0, len(z), chunk):
            part = slice(first, first + chunk)
            _splat_footprints(buffer, color_k, offsets, u[part], v[part], z[part], width_u[part], width_v[part])
    buffer[np.isinf(buffer)] = 0.0
    return buffer.reshape(color_k.height, color_k.width)


def _splat_footprints(
    buffer: np.ndarray, color_k: Intrinsics, offsets: np.ndarray,
    u: np.ndarray, v: np.ndarray, z: np.ndarray, width_u: np.ndarray, width_v: np.ndarray,
) -> None:
    """Write each sample's depth into every colour pixel its footprint covers (nearest surface kept)."""
    cells_u = np.floor(u)
    cells_v = np.floor(v)
    du = (cells_u[None, :] + offsets[:, None] + 0.5) - u[None, :]
    dv = (cells_v[None, :] + offsets[:, None] + 0.5) - v[None, :]
    in_u = (offsets[:, None] == 0) | ((du >= -width_u / 2) & (du < width_u / 2))
    in_v = (offsets[:, None] == 0) | ((dv >= -width_v / 2) & (dv < width_v / 2))
    keep = in_v[:, None, :] & in_u[None, :, :]
    pick_v, pick_u, sample = np.nonzero(keep)
    _splat(buffer, color_k, cells_u[sample] + offsets[pick_u], cells_v[sample] + offsets[pick_v], z[sample])


def _splat(buffer: np.ndarray, color_k: Intrinsics, cols: np.ndarray, rows: np.ndarray, z: np.ndarray) -> None:
    """Keep the nearest of ``z`` per colour pixel (cols, rows) inside the image, in the flat ``buffer``."""
    inside = (cols >= 0) & (cols < color_k.width) & (rows >= 0) & (rows < color_k.height)
    flat = rows[inside].astype(np.int64) * color_k.width + cols[inside].astype(np.int64)
    np.minimum.at(buffer, flat, z[inside])


def register_depth(frame: Frame) -> Frame:
    """The frame with depth re-projected onto the colour grid; unchanged if already registered."""
    if frame.registered:
        return frame
    depth = reproject_depth(frame.depth, frame.depth_intrinsics, frame.color_intrinsics, frame.depth_to_color)
    return dataclasses.replace(
        frame, depth=depth, depth_intrinsics=frame.color_intrinsics, depth_to_color=None
    )


def prepare(frame: Frame, depth_min: float, depth_max: float) -> Frame:
    """The frame as the mapper uses it and as evaluation scores against: depth registered onto the
    colour grid, then clipped to the working range."""
    return clip_depth(register_depth(frame), depth_min, depth_max)
