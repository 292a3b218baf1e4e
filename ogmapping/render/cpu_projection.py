"""Numba EWA projection for the cpu backend: ``projection.project_gaussians`` fused into one kernel.

The torch projection is ~100 small elementwise ops forward and as many backward, each paying
dispatch and a pass over memory; here one parallel loop does a Gaussian's whole projection in
registers, and the backward recomputes the forward terms it needs instead of storing them.

Exactness: the arithmetic follows ``projection.py`` operation by operation in float32 (float32
constants, no fastmath, so nothing is promoted or reassociated), and the radius in float64, so
outputs agree with the torch projection to float32 rounding and culling is the same. The backward
is the chain rule of exactly those operations, including torch's conventions at the kinks:
the Jacobian's clamped x/z, y/z pass gradient only inside their (inclusive) limits, culled
Gaussians' constant stand-ins (z := 1 behind the near plane, det := 1 when invalid) pass none,
and quaternions below the normalisation epsilon are divided by it. Opacity only gates validity
and sizes the integer radius, so the projection gives it no gradient.

The viewmat's gradient (for pose refinement) is computed only when asked for: each Gaussian's
float32 terms (through its camera-frame centre and the Jacobian's rows) summed in float64 per
view. Asking for it adds operations after the others and changes none of them, so the Gaussians'
gradients are the same bits with or without it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from ogmapping.render.projection import FOV_MARGIN, RADIUS_CAP
from ogmapping.render.rules import ALPHA_MIN, NEAR_PLANE

_ZERO = np.float32(0.0)
_ONE = np.float32(1.0)
_TWO = np.float32(2.0)
_NEAR = np.float32(NEAR_PLANE)
_ALPHA_MIN = np.float32(ALPHA_MIN)
_MARGIN = np.float32(FOV_MARGIN)
# torch.nn.functional.normalize's default epsilon.
_NORM_EPS = np.float32(1e-12)


@njit(cache=True, error_model="numpy")
def _clamp_limits(K, width, height):
    """Limits of x/z and y/z in the Jacobian: the image plus FOV_MARGIN of its half-width beyond."""
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    half_tan_x = np.float32(0.5 * width) / fx
    half_tan_y = np.float32(0.5 * height) / fy
    lo_x = -(cx / fx + _MARGIN * half_tan_x)
    hi_x = (np.float32(width) - cx) / fx + _MARGIN * half_tan_x
    lo_y = -(cy / fy + _MARGIN * half_tan_y)
    hi_y = (np.float32(height) - cy) / fy + _MARGIN * half_tan_y
    return lo_x, hi_x, lo_y, hi_y


@njit(cache=True, error_model="numpy")
def _unit_quat(quats, i):
    """Normalised (w, x, y, z) and the norm before clamping, as ``F.normalize`` computes them."""
    w, x, y, z = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
    norm = np.sqrt(w * w + x * x + y * y + z * z)
    d = max(norm, _NORM_EPS)
    return w / d, x / d, y / d, z / d, norm


@njit(cache=True, error_model="numpy")
def _rotation(w, x, y, z):
    """Row-major rotation matrix entries of a unit quaternion (``rotation.quaternion_entries``)."""
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return (
        _ONE - _TWO * (yy + zz), _TWO * (xy - wz), _TWO * (xz + wy),
        _TWO * (xy + wz), _ONE - _TWO * (xx + zz), _TWO * (yz - wx),
        _TWO * (xz - wy), _TWO * (yz + wx), _ONE - _TWO * (xx + yy),
    )


@njit(cache=True, error_model="numpy")
def _camera(means, i, viewmat):
    """Camera-frame centre, and the depth the projection divides by (1 behind the near plane)."""
    mx, my, mz = means[i, 0], means[i, 1], means[i, 2]
    x = viewmat[0, 0] * mx + viewmat[0, 1] * my + viewmat[0, 2] * mz + viewmat[0, 3]
    y = viewmat[1, 0] * mx + viewmat[1, 1] * my + viewmat[1, 2] * mz + viewmat[1, 3]
    z = viewmat[2, 0] * mx + viewmat[2, 1] * my + viewmat[2, 2] * mz + viewmat[2, 3]
    in_front = z >= _NEAR
    z_safe = z if in_front else _ONE
    return x, y, z, in_front, z_safe


@njit(cache=True, error_model="numpy")
def _radius(u, v, a, b, c, opacity, width, height):
    """``projection._radii`` for one valid Gaussian, in float64; 0 when it cannot touch the image."""
    a, b, c = np.float64(a), np.float64(b), np.float64(c)
    u, v = np.float64(u), np.float64(v)
    if not (np.isfinite(a) and np.isfinite(b) and np.isfinite(c) and np.isfinite(u) and np.isfinite(v)):
        return 0
    lambda_max = 0.5 * (a + c) + np.sqrt(max(0.25 * (a - c) ** 2 + b * b, 0.0))
    ratio = max(np.float64(opacity) / ALPHA_MIN, 1.0)
    extent = np.sqrt(2.0 * np.log(ratio)) * np.sqrt(max(lambda_max, 0.0))
    if not np.isfinite(extent):
        return 0
    radius = min(max(np.ceil(extent), 1.0), float(RADIUS_CAP))
    if u + radius > 0 and u - radius < width and v + radius > 0 and v - radius < height:
        return np.int32(radius)
    return 0


class _Terms(NamedTuple):
    """One Gaussian's forward terms: what ``project_forward`` outputs and ``project_backward`` differentiates."""

    z: float  # camera-frame depth
    in_front: bool
    z_safe: float  # the depth divided by: 1 behind the near plane
    x_z: float
    y_z: float
    tx: float  # x/z, y/z clamped to the Jacobian's limits
    ty: float
    gx: float  # fx / z, fy / z
    gy: float
    e: tuple  # rows of (W - clamped (x/z, y/z) W's third row): J W = (gx e[:3], gy e[3:])
    j: tuple  # J W, row-major 2x3
    q: tuple  # unit quaternion (w, x, y, z)
    norm: float  # its norm before normalising
    r: tuple  # its rotation, row-major 3x3
    s: tuple  # scales
    m: tuple  # J W R, row-major 2x3
    t: tuple  # T = J W R S, row-major 2x3
    a: float  # 2D covariance T T^T + blur: (a, b; b, c)
    b: float
    c: float
    valid: bool
    inv_det: float  # 1 / det, or 1 when invalid


@njit(cache=True, error_model="numpy", inline="always")
def _forward_terms(means, quats, scales, opacities, viewmat, fx, fy, limits, blur, i):
    """Gaussian ``i``'s ``_Terms``. Inlined into both kernels: called, its 50-odd values went through
    memory and the backward ran about 1.5x slower."""
    lo_x, hi_x, lo_y, hi_y = limits
    x, y, z, in_front, z_safe = _camera(means, i, viewmat)
    x_z = x / z_safe
    y_z = y / z_safe
    tx = min(max(x_z, lo_x), hi_x)
    ty = min(max(y_z, lo_y), hi_y)
    gx = fx / z_safe
    gy = fy / z_safe
    e00 = viewmat[0, 0] - tx * viewmat[2, 0]
    e01 = viewmat[0, 1] - tx * viewmat[2, 1]
    e02 = viewmat[0, 2] - tx * viewmat[2, 2]
    e10 = viewmat[1, 0] - ty * viewmat[2, 0]
    e11 = viewmat[1, 1] - ty * viewmat[2, 1]
    e12 = viewmat[1, 2] - ty * viewmat[2, 2]
    j00, j01, j02 = gx * e00, gx * e01, gx * e02
    j10, j11, j12 = gy * e10, gy * e11, gy * e12
    qw, qx, qy, qz, norm = _unit_quat(quats, i)
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = _rotation(qw, qx, qy, qz)
    s0, s1, s2 = scales[i, 0], scales[i, 1], scales[i, 2]
    m00 = j00 * r00 + j01 * r10 + j02 * r20
    m01 = j00 * r01 + j01 * r11 + j02 * r21
    m02 = j00 * r02 + j01 * r12 + j02 * r22
    m10 = j10 * r00 + j11 * r10 + j12 * r20
    m11 = j10 * r01 + j11 * r11 + j12 * r21
    m12 = j10 * r02 + j11 * r12 + j12 * r22
    t00, t01, t02 = s0 * m00, s1 * m01, s2 * m02
    t10, t11, t12 = s0 * m10, s1 * m11, s2 * m12
    a = t00 * t00 + t01 * t01 + t02 * t02 + blur
    b = t00 * t10 + t01 * t11 + t02 * t12
    c = t10 * t10 + t11 * t11 + t12 * t12 + blur
    det = a * c - b * b
    valid = in_front and det > _ZERO and opacities[i] >= _ALPHA_MIN
    inv_det = _ONE / (det if valid else _ONE)
    return _Terms(
        z, in_front, z_safe, x_z, y_z, tx, ty, gx, gy,
        (e00, e01, e02, e10, e11, e12), (j00, j01, j02, j10, j11, j12), (qw, qx, qy, qz), norm,
        (r00, r01, r02, r10, r11, r12, r20, r21, r22), (s0, s1, s2),
        (m00, m01, m02, m10, m11, m12), (t00, t01, t02, t10, t11, t12), a, b, c, valid, inv_det,
    )


@njit(parallel=True, cache=True, error_model="numpy")
def project_forward(means, quats, scales, opacities, viewmat, K, width, height, blur):
    """Screen-space means (N, 2), conics (N, 3), depths (N,) and int32 radii (N,), 0 = culled; ``blur``
    (pixels^2, any float) is added to each 2D covariance in float32."""
    n = means.shape[0]
    means2d = np.empty((n, 2), np.float32)
    conics = np.empty((n, 3), np.float32)
    depths = np.empty(n, np.float32)
    radii = np.zeros(n, np.int32)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    limits = _clamp_limits(K, width, height)
    blur32 = np.float32(blur)
    for i in prange(n):
        f = _forward_terms(means, quats, scales, opacities, viewmat, fx, fy, limits, blur32, i)
        u = fx * f.x_z + cx
        v = fy * f.y_z + cy
        means2d[i, 0] = u
        means2d[i, 1] = v
        conics[i, 0] = f.c * f.inv_det
        conics[i, 1] = -f.b * f.inv_det
        conics[i, 2] = f.a * f.inv_det
        depths[i] = f.z
        if f.valid:
            radii[i] = _radius(u, v, f.a, f.b, f.c, opacities[i], width, height)
    return means2d, conics, depths, radii


@njit(parallel=True, cache=True, error_model="numpy")
def project_backward(means, quats, scales, opacities, viewmat, K, width, height, blur, grad_means2d, grad_conics,
                     grad_depths, camera):
    """Gradients w.r.t. means (N, 3), quats (N, 4), scales (N, 3) and, where ``camera``, the viewmat
    (4, 4, float64; zeros otherwise) of ``project_forward``'s outputs.

    Recomputes each Gaussian's forward terms; Gaussians with no incoming gradient (all culled ones,
    in the renderer) are skipped. Each Gaussian's viewmat terms go to its own row, summed after the
    parallel loop, so no two threads write one entry.
    """
    n = means.shape[0]
    grad_means = np.zeros((n, 3), np.float32)
    grad_quats = np.zeros((n, 4), np.float32)
    grad_scales = np.zeros((n, 3), np.float32)
    camera_terms = np.zeros((n if camera else 0, 12), np.float32)
    fx, fy = K[0, 0], K[1, 1]
    limits = _clamp_limits(K, width, height)
    lo_x, hi_x, lo_y, hi_y = limits
    blur32 = np.float32(blur)
    for i in prange(n):
        gu, gv, gd = grad_means2d[i, 0], grad_means2d[i, 1], grad_depths[i]
        gca, gcb, gcc = grad_conics[i, 0], grad_conics[i, 1], grad_conics[i, 2]
        if gu == _ZERO and gv == _ZERO and gd == _ZERO and gca == _ZERO and gcb == _ZERO and gcc == _ZERO:
            continue
        f = _forward_terms(means, quats, scales, opacities, viewmat, fx, fy, limits, blur32, i)
        x_z, y_z, gx, gy, z_safe, a, b, c, inv_det = f.x_z, f.y_z, f.gx, f.gy, f.z_safe, f.a, f.b, f.c, f.inv_det
        e00, e01, e02, e10, e11, e12 = f.e
        j00, j01, j02, j10, j11, j12 = f.j
        qw, qx, qy, qz = f.q
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = f.r
        s0, s1, s2 = f.s
        m00, m01, m02, m10, m11, m12 = f.m
        t00, t01, t02, t10, t11, t12 = f.t

        # Conic (c, -b, a) / det -> 2D covariance.
        g_a = gcc * inv_det
        g_b = -gcb * inv_det
        g_c = gca * inv_det
        if f.valid:
            g_det = -(gca * c - gcb * b + gcc * a) * inv_det * inv_det
            g_a += g_det * c
            g_c += g_det * a
            g_b -= _TWO * b * g_det
        # Covariance T T^T -> rows of T = J W R S.
        g_t00 = _TWO * t00 * g_a + t10 * g_b
        g_t01 = _TWO * t01 * g_a + t11 * g_b
        g_t02 = _TWO * t02 * g_a + t12 * g_b
        g_t10 = _TWO * t10 * g_c + t00 * g_b
        g_t11 = _TWO * t11 * g_c + t01 * g_b
        g_t12 = _TWO * t12 * g_c + t02 * g_b
        grad_scales[i, 0] = g_t00 * m00 + g_t10 * m10
        grad_scales[i, 1] = g_t01 * m01 + g_t11 * m11
        grad_scales[i, 2] = g_t02 * m02 + g_t12 * m12
        g_m00, g_m01, g_m02 = g_t00 * s0, g_t01 * s1, g_t02 * s2
        g_m10, g_m11, g_m12 = g_t10 * s0, g_t11 * s1, g_t12 * s2
        # M = (J W) R: to the Jacobian rows and to the rotation.
        g_j00 = g_m00 * r00 + g_m01 * r01 + g_m02 * r02
        g_j01 = g_m00 * r10 + g_m01 * r11 + g_m02 * r12
        g_j02 = g_m00 * r20 + g_m01 * r21 + g_m02 * r22
        g_j10 = g_m10 * r00 + g_m11 * r01 + g_m12 * r02
        g_j11 = g_m10 * r10 + g_m11 * r11 + g_m12 * r12
        g_j12 = g_m10 * r20 + g_m11 * r21 + g_m12 * r22
        g_r00, g_r01, g_r02 = g_m00 * j00 + g_m10 * j10, g_m01 * j00 + g_m11 * j10, g_m02 * j00 + g_m12 * j10
        g_r10, g_r11, g_r12 = g_m00 * j01 + g_m10 * j11, g_m01 * j01 + g_m11 * j11, g_m02 * j01 + g_m12 * j11
        g_r20, g_r21, g_r22 = g_m00 * j02 + g_m10 * j12, g_m01 * j02 + g_m11 * j12, g_m02 * j02 + g_m12 * j12
        _quat_backward(grad_quats, i, quats, f.norm, qw, qx, qy, qz,
                       g_r00, g_r01, g_r02, g_r10, g_r11, g_r12, g_r20, g_r21, g_r22)

        # J W rows -> focal-over-depth factors and the clamped x/z, y/z.
        g_gx = g_j00 * e00 + g_j01 * e01 + g_j02 * e02
        g_gy = g_j10 * e10 + g_j11 * e11 + g_j12 * e12
        g_xz = fx * gu
        g_yz = fy * gv
        if lo_x <= x_z <= hi_x:
            g_xz -= gx * (g_j00 * viewmat[2, 0] + g_j01 * viewmat[2, 1] + g_j02 * viewmat[2, 2])
        if lo_y <= y_z <= hi_y:
            g_yz -= gy * (g_j10 * viewmat[2, 0] + g_j11 * viewmat[2, 1] + g_j12 * viewmat[2, 2])
        g_x = g_xz / z_safe
        g_y = g_yz / z_safe
        g_z = gd
        if f.in_front:
            g_z -= (g_xz * x_z + g_yz * y_z + g_gx * gx + g_gy * gy) / z_safe
        for k in range(3):
            grad_means[i, k] = viewmat[0, k] * g_x + viewmat[1, k] * g_y + viewmat[2, k] * g_z
        if camera:
            _camera_backward(camera_terms, i, means, f.tx, f.ty, g_x, g_y, g_z,
                             gx * g_j00, gx * g_j01, gx * g_j02, gy * g_j10, gy * g_j11, gy * g_j12)
    grad_viewmat = np.zeros((4, 4), np.float64)
    for i in range(camera_terms.shape[0]):
        for k in range(12):
            grad_viewmat[k // 4, k % 4] += camera_terms[i, k]
    return grad_means, grad_quats, grad_scales, grad_viewmat


@njit(cache=True, error_model="numpy")
def _camera_backward(terms, i, means, tx, ty, g_x, g_y, g_z, g_e00, g_e01, g_e02, g_e10, g_e11, g_e12):
    """Gaussian ``i``'s part of the viewmat gradient, rows 0-2 of (4, 4) row-major into ``terms[i]``.

    The viewmat enters twice: the camera-frame centre (x, y, z) = W m + t, whose gradient is
    (g_x, g_y, g_z), and the Jacobian rows e0k = W0k - tx W2k, e1k = W1k - ty W2k, whose gradient
    is g_e; tx, ty are the clamped x/z, y/z, whose own gradient already reached (g_x, g_y, g_z).
    """
    m0, m1, m2 = means[i, 0], means[i, 1], means[i, 2]
    terms[i, 0], terms[i, 1], terms[i, 2], terms[i, 3] = g_x * m0 + g_e00, g_x * m1 + g_e01, g_x * m2 + g_e02, g_x
    terms[i, 4], terms[i, 5], terms[i, 6], terms[i, 7] = g_y * m0 + g_e10, g_y * m1 + g_e11, g_y * m2 + g_e12, g_y
    terms[i, 8] = g_z * m0 - tx * g_e00 - ty * g_e10
    terms[i, 9] = g_z * m1 - tx * g_e01 - ty * g_e11
    terms[i, 10] = g_z * m2 - tx * g_e02 - ty * g_e12
    terms[i, 11] = g_z


@njit(cache=True, error_model="numpy")
def _quat_backward(grad_quats, i, quats, norm, w, x, y, z, g00, g01, g02, g10, g11, g12, g20, g21, g22):
    """Rotation-entry gradients -> unit quaternion -> raw quaternion (through the normalisation)."""
    gw = _TWO * (-z * g01 + y * g02 + z * g10 - x * g12 - y * g20 + x * g21)
    gx = _TWO * (y * g01 + z * g02 + y * g10 - _TWO * x * g11 - w * g12 + z * g20 + w * g21 - _TWO * x * g22)
    gy = _TWO * (-_TWO * y * g00 + x * g01 + w * g02 + x * g10 + z * g12 - w * g20 + z * g21 - _TWO * y * g22)
    gz = _TWO * (-_TWO * z * g00 - w * g01 + x * g02 + w * g10 - _TWO * z * g11 + y * g12 + x * g20 + y * g21)
    if norm >= _NORM_EPS:
        radial = w * gw + x * gx + y * gy + z * gz
        grad_quats[i, 0] = (gw - w * radial) / norm
        grad_quats[i, 1] = (gx - x * radial) / norm
        grad_quats[i, 2] = (gy - y * radial) / norm
        grad_quats[i, 3] = (gz - z * radial) / norm
    else:
        grad_quats[i, 0] = gw / _NORM_EPS
        grad_quats[i, 1] = gx / _NORM_EPS
        grad_quats[i, 2] = gy / _NORM_EPS
        grad_quats[i, 3] = gz / _NORM_EPS
