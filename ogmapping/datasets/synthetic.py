"""A synthetic RGB-D sequence with exact depth and poses, so tests and demos need no download.

The scene is a 6 x 5 x 3 m room (world z up, floor at z = 0) holding boxes, spheres and a
cylinder, ray-cast analytically in numpy. Textures mix smooth gradients, mid-frequency sinusoids
and soft-edged stripes, checkers and planks of 20-40 cm period: content a Gaussian map with ~10 cm
coarse voxels can learn, with no per-pixel noise. Shading is view-independent (one point light
plus ambient, no shadows), so every view of a surface point sees the same colour.

The camera orbits near the room centre looking outward, with gentle height, pitch, roll and yaw
changes, moving a few cm and 1-3 degrees per frame like a handheld scan. Depth is the exact z
along the camera axis at each pixel centre; colour and depth share one camera (registered).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ogmapping.datasets.base import CameraSource
from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.frame import Frame

ROOM_LO = np.array([-3.0, -2.5, 0.0])
ROOM_HI = np.array([3.0, 2.5, 3.0])
LIGHT = np.array([0.2, -0.1, 2.7])
HORIZONTAL_FOV_DEG = 65.0
FPS = 30.0

Texture = Callable[[np.ndarray, np.ndarray], np.ndarray]


def _soft_square(x: np.ndarray, period: float, sharpness: float = 6.0) -> np.ndarray:
    """A square wave in [0, 1] with edges a few percent of the period wide (no aliasing speckle)."""
    return 0.5 + 0.5 * np.tanh(sharpness * np.sin(2.0 * np.pi * x / period))


def _soft_box(x: np.ndarray, lo: float, hi: float, edge: float = 0.01) -> np.ndarray:
    """About 1 inside [lo, hi] and 0 outside, with edges ``edge`` metres soft."""
    return 0.25 * (1.0 + np.tanh((x - lo) / edge)) * (1.0 + np.tanh((hi - x) / edge))


def _hash(cell: np.ndarray, salt: float) -> np.ndarray:
    """A deterministic pseudo-random value in [0, 1) per integer cell."""
    value = np.sin(cell * 12.9898 + salt * 78.233) * 43758.5453
    return value - np.floor(value)


def _mix(a: np.ndarray, b: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Blend colours ``a`` and ``b`` (3,) per point by ``weight`` (N,)."""
    return a[None, :] * (1.0 - weight[:, None]) + b[None, :] * weight[:, None]


def _face_coords(points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two in-face coordinates of points on axis-aligned faces (the axes the normal does not use)."""
    axis = np.argmax(np.abs(normals), axis=1)
    first = np.where(axis == 0, points[:, 1], points[:, 0])
    second = np.where(axis == 2, points[:, 1], points[:, 2])
    return first, second


@dataclass
class Rays:
    """Rays from one origin, stored component-major (3, N) so per-axis work runs on contiguous rows."""

    origin: np.ndarray
    dirs: np.ndarray
    inv: np.ndarray  # 1 / dirs, with exact zeros nudged so no inf or nan arises

    @classmethod
    def make(cls, origin: np.ndarray, dirs: np.ndarray) -> Rays:
        safe = np.where(dirs == 0.0, 1e-12, dirs)
        return cls(np.asarray(origin, dtype=np.float64), dirs, 1.0 / safe)


@dataclass
class Box:
    lo: np.ndarray
    hi: np.ndarray
    texture: Texture

    def distance(self, rays: Rays) -> np.ndarray:
        """Entry distance along each ray, inf on a miss (slab test)."""
        t_enter = t_exit = None
        for k in range(3):
            t1 = (self.lo[k] - rays.origin[k]) * rays.inv[k]
            t2 = (self.hi[k] - rays.origin[k]) * rays.inv[k]
            near, far = np.minimum(t1, t2), np.maximum(t1, t2)
            t_enter = near if t_enter is None else np.maximum(t_enter, near)
            t_exit = far if t_exit is None else np.minimum(t_exit, far)
        return np.where((t_enter <= t_exit) & (t_enter > 0), t_enter, np.inf)

    def normals(self, points: np.ndarray) -> np.ndarray:
        """Outward normal of the face each surface point lies on."""
        gaps = np.abs(np.concatenate([points - self.lo, points - self.hi], axis=1))
        face = gaps.argmin(axis=1)
        normals = np.zeros_like(points)
        normals[np.arange(len(points)), face % 3] = np.where(face < 3, -1.0, 1.0)
        return normals


@dataclass
class Sphere:
    centre: np.ndarray
    radius: float
    texture: Texture

    def distance(self, rays: Rays) -> np.ndarray:
        offset = rays.origin - self.centre
        a = np.einsum("ij,ij->j", rays.dirs, rays.dirs)
        b = 2.0 * np.einsum("i,in->n", offset, rays.dirs)
        c = offset @ offset - self.radius**2
        disc = b * b - 4.0 * a * c
        t = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * a)
        return np.where((disc >= 0) & (t > 0), t, np.inf)

    def normals(self, points: np.ndarray) -> np.ndarray:
        return (points - self.centre) / self.radius


@dataclass
class Cylinder:
    """An upright cylinder standing on the floor, with a top cap."""

    centre: np.ndarray  # (x, y)
    radius: float
    height: float
    texture: Texture

    def distance(self, rays: Rays) -> np.ndarray:
        ox, oy, oz = rays.origin[0] - self.centre[0], rays.origin[1] - self.centre[1], rays.origin[2]
        dx, dy, dz = rays.dirs
        a = dx * dx + dy * dy + 1e-18
        b = 2.0 * (dx * ox + dy * oy)
        c = ox * ox + oy * oy - self.radius**2
        disc = b * b - 4.0 * a * c
        t_side = (-b - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * a)
        z_side = oz + t_side * dz
        side_ok = (disc >= 0) & (t_side > 0) & (z_side >= 0) & (z_side <= self.height)
        t_top = (self.height - oz) * rays.inv[2]
        top_x, top_y = ox + t_top * dx, oy + t_top * dy
        top_ok = (t_top > 0) & (top_x * top_x + top_y * top_y <= self.radius**2)
        return np.minimum(np.where(side_ok, t_side, np.inf), np.where(top_ok, t_top, np.inf))

    def normals(self, points: np.ndarray) -> np.ndarray:
        normals = np.zeros_like(points)
        normals[:, 0] = (points[:, 0] - self.centre[0]) / self.radius
        normals[:, 1] = (points[:, 1] - self.centre[1]) / self.radius
        normals[points[:, 2] >= self.height - 1e-6] = (0.0, 0.0, 1.0)
        return normals


Shape = Box | Sphere | Cylinder


def _floor_box(centre: np.ndarray, half_x_half_y_height: tuple[float, float, float], texture: Texture) -> Box:
    """A box standing on the floor around ``centre`` (x, y, 0)."""
    half_x, half_y, height = half_x_half_y_height
    return Box(centre + np.array([-half_x, -half_y, 0.0]), centre + np.array([half_x, half_y, height]), texture)


class SyntheticScene:
    """The room and its objects, with colours varied per seed."""

    def __init__(self, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        self.salt = float(rng.uniform(0.0, 10.0))

        def tint(rgb: tuple[float, float, float]) -> np.ndarray:
            return np.clip(np.asarray(rgb) + rng.uniform(-0.06, 0.06, 3), 0.05, 0.95)

        def jitter() -> np.ndarray:
            return np.array([*rng.uniform(-0.15, 0.15, 2), 0.0])

        self.wall_colors = [tint(c) for c in ((0.80, 0.74, 0.62), (0.55, 0.68, 0.78), (0.78, 0.60, 0.55),
                                              (0.62, 0.75, 0.58))]
        table = jitter() + np.array([1.9, 1.2, 0.0])
        cabinet = jitter() + np.array([-2.3, -1.5, 0.0])
        crate = jitter() + np.array([-1.8, 1.6, 0.0])
        ball = jitter() + np.array([2.0, -1.4, 0.45])
        pillar = jitter()[:2] + np.array([0.4, -1.95])
        self.shapes: list[Shape] = [
            _floor_box(table, (0.5, 0.35, 0.75),
                       self._checker_texture(tint((0.60, 0.42, 0.28)), tint((0.42, 0.28, 0.18)), 0.4)),
            _floor_box(cabinet, (0.4, 0.5, 1.3),
                       self._stripe_texture(tint((0.75, 0.22, 0.18)), tint((0.90, 0.85, 0.80)), 0.3)),
            _floor_box(crate, (0.35, 0.3, 0.5),
                       self._checker_texture(tint((0.25, 0.45, 0.70)), tint((0.85, 0.80, 0.40)), 0.2)),
            Sphere(table + np.array([0.0, 0.0, 0.97]), 0.22, self._band_texture(tint((0.9, 0.55, 0.15)), 0.1)),
            Sphere(ball, 0.45, self._band_texture(tint((0.3, 0.7, 0.4)), 0.2)),
            Cylinder(pillar, 0.25, 1.6, self._pillar_texture(tint((0.45, 0.35, 0.65)))),
        ]

    # Textures: each maps surface points and normals (N, 3) to albedo (N, 3).

    @staticmethod
    def _checker_texture(a: np.ndarray, b: np.ndarray, period: float) -> Texture:
        def texture(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
            u, v = _face_coords(points, normals)
            weight = 0.5 + 0.5 * np.tanh(5.0 * np.sin(2 * np.pi * u / period) * np.sin(2 * np.pi * v / period))
            return _mix(a, b, weight)

        return texture

    @staticmethod
    def _stripe_texture(a: np.ndarray, b: np.ndarray, period: float) -> Texture:
        def texture(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
            weight = _soft_square(points[:, 2], period, 8.0)
            gradient = 0.85 + 0.15 * np.sin(points[:, 0] * 1.3 + points[:, 1] * 0.9)
            return _mix(a, b, weight) * gradient[:, None]

        return texture

    @staticmethod
    def _band_texture(base: np.ndarray, period: float) -> Texture:
        def texture(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
            weight = 0.5 + 0.5 * np.sin(2 * np.pi * points[:, 2] / period)
            light = np.clip(base + 0.3, 0.0, 1.0)
            return _mix(base, light, weight) * (0.875 + 0.125 * normals[:, 0])[:, None]

        return texture

    @staticmethod
    def _pillar_texture(base: np.ndarray) -> Texture:
        def texture(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
            angle = np.arctan2(normals[:, 1], normals[:, 0])
            weight = _soft_square(angle, 2 * np.pi / 6, 5.0) * (normals[:, 2] < 0.5)
            height = 0.8 + 0.2 * np.cos(points[:, 2] * 2.0)
            return _mix(base, np.array([0.92, 0.92, 0.88]), weight) * height[:, None]

        return texture

    def _room_albedo(self, points: np.ndarray, face: np.ndarray) -> np.ndarray:
        """Albedo on the room's faces: 0..3 walls (-x, +x, -y, +y), 4 floor, 5 ceiling."""
        albedo = np.empty_like(points)
        for index, paint in enumerate(
            (self._wallpaper, self._wainscot, self._stripes, self._poster_wall, self._planks, self._ceiling)
        ):
            mask = face == index
            if mask.any():
                x, y, z = points[mask].T
                along = y if index < 2 else x
                colour = paint(along, z, x, y)
                albedo[mask] = colour if colour.ndim == 2 else self.wall_colors[index][None, :] * colour[:, None]
        return albedo

    # Room faces: each returns a brightness (N,) scaling the wall colour, or an albedo (N, 3).

    @staticmethod
    def _wallpaper(along: np.ndarray, z: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """A mid-frequency sinusoid pattern over a vertical gradient."""
        return 0.75 + 0.25 * np.sin(2 * np.pi * along / 0.35) * np.sin(2 * np.pi * z / 0.35) - 0.05 * z

    @staticmethod
    def _wainscot(along: np.ndarray, z: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """A soft checker below 1 m, a smooth gradient above."""
        checker = 0.6 + 0.4 * _soft_square(along, 0.4) * _soft_square(z, 0.4)
        return np.where(z < 1.0, checker, 0.85 + 0.1 * np.cos(along * 0.8))

    @staticmethod
    def _stripes(along: np.ndarray, z: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Vertical stripes with fairly sharp edges, fading with height."""
        return 0.7 + 0.3 * _soft_square(along, 0.3, 8.0) * (1.0 - 0.2 * z)

    def _poster_wall(self, along: np.ndarray, z: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """A two-way gradient with a colourful poster whose border is sharp."""
        wall = self.wall_colors[3][None, :] * (0.75 + 0.1 * np.sin(along * 1.1) + 0.1 * np.cos(z * 1.5))[:, None]
        art = np.stack(
            [0.5 + 0.4 * np.sin(along * 9.0), 0.3 + 0.2 * np.cos(z * 7.0), 0.6 + 0.3 * np.sin((along + z) * 5.0)],
            axis=1,
        )
        poster = (_soft_box(along, -0.8, 0.8) * _soft_box(z, 1.0, 2.0))[:, None]
        return wall * (1.0 - poster) + art * poster

    def _planks(self, along: np.ndarray, z: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Floor planks: per-plank tone (sharp seams) and a sinusoid grain."""
        plank = np.floor(y / 0.22)
        tone = 0.8 + 0.35 * _hash(plank, self.salt)
        grain = 1.0 + 0.07 * np.sin(2 * np.pi * (x / 0.13 + 0.4 * np.sin(2 * np.pi * y / 0.9)))
        border = np.abs(y / 0.22 - np.round(y / 0.22))
        seam = 1.0 - 0.4 * np.exp(-((border / 0.05) ** 2))
        return np.array([0.58, 0.40, 0.24])[None, :] * (tone * grain * seam)[:, None]

    @staticmethod
    def _ceiling(along: np.ndarray, z: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Off-white with a gentle radial gradient."""
        return np.array([0.92, 0.90, 0.86])[None, :] * (1.0 - 0.06 * np.hypot(x, y))[:, None]

    def raycast(self, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance in units of ``dirs`` (3, N) to the first surface along each ray, and its colour (N, 3)."""
        rays = Rays.make(origin, dirs)
        exits = [
            np.where(rays.dirs[k] > 0, ROOM_HI[k] - origin[k], ROOM_LO[k] - origin[k]) * rays.inv[k] for k in range(3)
        ]
        axis = np.where(exits[0] <= exits[1], 0, 1)
        t = np.minimum(exits[0], exits[1])
        axis = np.where(exits[2] < t, 2, axis)
        t = np.minimum(t, exits[2])
        positive = np.take_along_axis(rays.dirs, axis[None, :], axis=0)[0] > 0
        face = 2 * axis + positive

        shape_id = np.full(t.shape, -1)
        for index, shape in enumerate(self.shapes):
            t_shape = shape.distance(rays)
            closer = t_shape < t
            t = np.where(closer, t_shape, t)
            shape_id[closer] = index

        points = (origin[:, None] + rays.dirs * t[None, :]).T
        albedo = np.empty_like(points)
        normals = np.zeros_like(points)
        on_room = shape_id < 0
        albedo[on_room] = self._room_albedo(points[on_room], face[on_room])
        room_axis = axis[on_room]
        normals[np.flatnonzero(on_room), room_axis] = np.where(positive[on_room], -1.0, 1.0)
        for index, shape in enumerate(self.shapes):
            mask = shape_id == index
            if mask.any():
                normals[mask] = shape.normals(points[mask])
                albedo[mask] = shape.texture(points[mask], normals[mask])
        to_light = LIGHT - points
        distance = np.sqrt(np.einsum("ij,ij->i", to_light, to_light))
        lambert = np.maximum(np.einsum("ij,ij->i", normals, to_light) / distance, 0.0)
        shade = 0.45 + 0.75 * lambert / (1.0 + 0.04 * distance**2)
        return t, np.clip(albedo * shade[:, None], 0.0, 1.0)


def _look(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """Camera-to-world rotation (OpenCV camera axes) looking along yaw/pitch in a z-up world."""
    forward = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)])
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    c, s = math.cos(roll), math.sin(roll)
    return np.stack([c * right + s * down, -s * right + c * down, forward], axis=1)


def trajectory(n_frames: int, seed: int = 0) -> np.ndarray:
    """Camera-to-world poses (n, 4, 4) of a slow outward-looking orbit near the room centre."""
    rng = np.random.default_rng(seed + 7919)
    phases = rng.uniform(0.0, 2 * np.pi, 5)
    centre = rng.uniform(-0.15, 0.15, 2)
    yaw_rate = math.radians(min(max(300.0 / max(n_frames, 1), 0.8), 2.8))
    poses = np.zeros((n_frames, 4, 4))
    for i in range(n_frames):
        angle = phases[0] + yaw_rate * i
        radius = 0.7 + 0.12 * math.sin(0.5 * angle + phases[1])
        position = [
            centre[0] + radius * math.cos(angle),
            centre[1] + radius * math.sin(angle),
            1.45 + 0.15 * math.sin(2 * np.pi * i / 97.0 + phases[2]),
        ]
        yaw = angle + 0.12 * math.sin(2 * np.pi * i / 90.0 + phases[3])
        pitch = -0.15 + 0.1 * math.sin(2 * np.pi * i / 70.0 + phases[4])
        roll = 0.03 * math.sin(2 * np.pi * i / 50.0)
        poses[i, :3, :3] = _look(yaw, pitch, roll)
        poses[i, :3, 3] = position
        poses[i, 3, 3] = 1.0
    return poses


def synthetic_intrinsics(width: int, height: int) -> Intrinsics:
    """A square-pixel pinhole with a 65 degree horizontal field of view, centred."""
    fx = 0.5 * width / math.tan(math.radians(HORIZONTAL_FOV_DEG) / 2)
    return Intrinsics(fx, fx, width / 2.0, height / 2.0, width, height)


class SyntheticSource(CameraSource):
    """Frames rendered on demand; the same seed always gives the same scene and path."""

    def __init__(self, n_frames: int = 100, width: int = 320, height: int = 240, seed: int = 0) -> None:
        if n_frames < 1 or width < 1 or height < 1:
            raise ValueError(f"synthetic needs n_frames, width, height >= 1 (got {n_frames}, {width}, {height})")
        self.name = f"synthetic:seed={seed}"
        self.scene = SyntheticScene(seed)
        self.poses = trajectory(n_frames, seed)
        k = self.color_intrinsics = self.depth_intrinsics = synthetic_intrinsics(width, height)
        u = (np.arange(width) + 0.5 - k.cx) / k.fx
        v = (np.arange(height) + 0.5 - k.cy) / k.fy
        grid_u, grid_v = np.meshgrid(u, v)
        self._rays = np.stack([grid_u.ravel(), grid_v.ravel(), np.ones(grid_u.size)])

    def __len__(self) -> int:
        return len(self.poses)

    def _load(self, position: int) -> Frame:
        c2w = self.poses[position]
        # Rays with camera z = 1, so the hit distance is the depth along the camera axis.
        dirs = np.einsum("ij,jn->in", c2w[:3, :3], self._rays)  # einsum: no BLAS threads for a 3x3
        depth, colour = self.scene.raycast(c2w[:3, 3], dirs)
        k = self.color_intrinsics
        rgb = colour.reshape(k.height, k.width, 3).astype(np.float32)
        depth_image = depth.reshape(k.height, k.width).astype(np.float32)
        return self._frame(position, rgb, depth_image, c2w.copy(), position / FPS)
