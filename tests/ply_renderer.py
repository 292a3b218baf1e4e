"""A small renderer for 3DGS .ply files, written from the public convention alone.

It imports nothing from ``ogmapping``: it stands for any third-party viewer. Convention (the 3DGS
paper's files): per vertex ``x, y, z``, ``f_dc_0..2`` (SH degree-0 coefficients; colour =
0.5 + C0 * f_dc, clamped at 0), ``opacity`` (a logit: sigmoid), ``scale_0..2`` (log standard
deviations: exp), ``rot_0..3`` (a (w, x, y, z) quaternion, normalised here). Rendering is EWA
splatting: the 3D covariance R S S^T R^T projected with the perspective Jacobian, plus 0.3 px^2 of
low-pass blur, composited front to back by camera depth with alpha = min(0.99, o exp(-d^T S^-1 d / 2)),
contributions under 1/255 skipped, a pixel done once its transmittance would fall below 1e-4.
Pixel centres are at +0.5 (x right, y down, z forward: OpenCV axes); background black.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

SH_C0 = 0.28209479177387814


def read_ply(path: str | Path) -> dict[str, np.ndarray]:
    """The vertex table of a binary little-endian .ply whose properties are all float32."""
    raw = Path(path).read_bytes()
    header, _, body = raw.partition(b"end_header\n")
    lines = header.decode("ascii").splitlines()
    assert lines[0] == "ply" and lines[1] == "format binary_little_endian 1.0"
    count = next(int(line.split()[2]) for line in lines if line.startswith("element vertex"))
    names = [line.split()[2] for line in lines if line.startswith("property float")]
    table = np.frombuffer(body, dtype=[(name, "<f4") for name in names], count=count)
    return {name: table[name].astype(np.float64) for name in names}


def rotation(q: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices of (N, 4) (w, x, y, z) quaternions."""
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], 1)


def render(ply: dict[str, np.ndarray], c2w: np.ndarray, fx: float, fy: float, cx: float, cy: float,
           width: int, height: int) -> np.ndarray:
    """(H, W, 3) colour of the .ply seen by a pinhole camera with pose ``c2w`` (camera to world)."""
    means = np.stack([ply["x"], ply["y"], ply["z"]], 1)
    colors = np.maximum(0.5 + SH_C0 * np.stack([ply[f"f_dc_{i}"] for i in range(3)], 1), 0.0)
    opacity = 1.0 / (1.0 + np.exp(-ply["opacity"]))
    scales = np.exp(np.stack([ply[f"scale_{i}"] for i in range(3)], 1))
    rot = rotation(np.stack([ply[f"rot_{i}"] for i in range(4)], 1))
    w2c = np.linalg.inv(c2w)
    cam = means @ w2c[:3, :3].T + w2c[:3, 3]
    keep = cam[:, 2] > 0.01
    cam, colors, opacity, scales, rot = cam[keep], colors[keep], opacity[keep], scales[keep], rot[keep]
    x, y, z = cam.T
    m = rot * scales[:, None, :]
    cov_world = m @ m.transpose(0, 2, 1)
    cov_cam = w2c[:3, :3] @ cov_world @ w2c[:3, :3].T
    jac = np.zeros((len(z), 2, 3))
    jac[:, 0, 0], jac[:, 0, 2] = fx / z, -fx * x / z**2
    jac[:, 1, 1], jac[:, 1, 2] = fy / z, -fy * y / z**2
    cov2d = jac @ cov_cam @ jac.transpose(0, 2, 1) + 0.3 * np.eye(2)
    u, v = fx * x / z + cx, fy * y / z + cy
    image = np.zeros((height, width, 3))
    transmittance = np.ones((height, width))
    alive = np.ones((height, width), dtype=bool)
    for g in np.argsort(z, kind="stable"):
        a, b, c = cov2d[g, 0, 0], cov2d[g, 0, 1], cov2d[g, 1, 1]
        det = a * c - b * b
        if det <= 0 or opacity[g] < 1 / 255:
            continue
        reach = np.sqrt(2 * np.log(255 * opacity[g]))  # sigmas at which alpha falls to 1/255
        rx, ry = reach * np.sqrt(a) + 1, reach * np.sqrt(c) + 1
        x0, x1 = max(int(u[g] - rx), 0), min(int(u[g] + rx) + 1, width)
        y0, y1 = max(int(v[g] - ry), 0), min(int(v[g] + ry) + 1, height)
        if x0 >= x1 or y0 >= y1:
            continue
        dx = np.arange(x0, x1) + 0.5 - u[g]
        dy = (np.arange(y0, y1) + 0.5 - v[g])[:, None]
        power = (c * dx * dx - 2 * b * dx * dy + a * dy * dy) / (2 * det)
        alpha = np.minimum(0.99, opacity[g] * np.exp(-power))
        t = transmittance[y0:y1, x0:x1]
        live = alive[y0:y1, x0:x1] & (alpha >= 1 / 255)
        done = live & (t * (1 - alpha) < 1e-4)
        live &= ~done
        weight = np.where(live, alpha * t, 0.0)
        image[y0:y1, x0:x1] += weight[..., None] * colors[g]
        transmittance[y0:y1, x0:x1] = np.where(live, t * (1 - alpha), t)
        alive[y0:y1, x0:x1] &= ~done
    return image
