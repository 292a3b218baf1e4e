"""Rotations in one place: quaternions, axis-angle (Rodrigues) and the matrix exponential, for numpy and torch.

Numpy callers (dataset readers, ROS bag transforms, trajectory files, the recorder's Foxglove
transforms) hold quaternions in ROS, TUM and Foxglove order (x, y, z, w); the renderer's Gaussians
hold them as (w, x, y, z) tensors. ``quaternion_entries`` and ``skew_entries`` are written with
arithmetic operators only, so the same formula serves numpy scalars and torch tensors (autograd
included) with the same float operations. The float operations are fixed: recordings hold the
quaternions ``matrix_to_quaternion`` produces, and maps depend on the rest.

torch is imported only inside the functions that build tensors, so the dataset readers and the
torch-free client load this module without it. The CPU rasterizer's Numba kernel
(``ogmapping.render.cpu_projection``) cannot call these and keeps a float32 copy of ``quaternion_entries``.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import torch


def quaternion_entries(w: Any, x: Any, y: Any, z: Any) -> list[list[Any]]:
    """Row-major 3x3 rotation entries of a unit quaternion; scalars or same-shaped arrays/tensors alike."""
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz = x * y, x * z, y * z
    wx, wy, wz = w * x, w * y, w * z
    return [
        [1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)],
        [2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)],
        [2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)],
    ]


def skew_entries(x: Any, y: Any, z: Any, zero: Any) -> list[list[Any]]:
    """Row-major entries of the cross-product matrix of (x, y, z); ``zero`` fills the diagonal."""
    return [[zero, -z, y], [z, zero, -x], [-y, x, zero]]


# numpy --------------------------------------------------------------------------------------------


def quaternion_to_matrix(qx: float, qy: float, qz: float, qw: float) -> np.ndarray:
    """3x3 rotation of a quaternion, normalised here."""
    q = np.array([qw, qx, qy, qz], dtype=np.float64)
    return np.array(quaternion_entries(*(q / np.linalg.norm(q))))


def quaternion_pose(translation: Any, quaternion: Any) -> np.ndarray:
    """4x4 camera-to-world (or child-in-parent) from a translation and an (x, y, z, w) quaternion."""
    pose = np.eye(4)
    pose[:3, :3] = quaternion_to_matrix(*quaternion)
    pose[:3, 3] = translation
    return pose


def matrix_to_quaternion(rotation: np.ndarray) -> tuple[float, float, float, float]:
    """Unit quaternion of a rotation matrix, branching on the largest diagonal term for stability."""
    r = np.asarray(rotation, dtype=np.float64)
    trace = r[0, 0] + r[1, 1] + r[2, 2]
    if trace > 0:
        s = 2.0 * np.sqrt(trace + 1.0)
        w, x, y, z = 0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * np.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        w, x, y, z = (r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * np.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        w, x, y, z = (r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s
    else:
        s = 2.0 * np.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        w, x, y, z = (r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s
    norm = float(np.sqrt(w * w + x * x + y * y + z * z))
    return x / norm, y / norm, z / norm, w / norm


def slerp(q0: np.ndarray, q1: np.ndarray, alpha: float) -> np.ndarray:
    """Spherical interpolation of unit quaternions, along the shorter arc."""
    dot = float(np.dot(q0, q1))
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly equal: the linear blend is exact to float precision
        q = q0 + alpha * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(dot)
    return (np.sin((1.0 - alpha) * theta) * q0 + np.sin(alpha * theta) * q1) / np.sin(theta)


def interpolate_pose(first: np.ndarray, second: np.ndarray, alpha: float) -> np.ndarray:
    """The 4x4 pose ``alpha`` of the way from ``first`` to ``second``: the translation along the line, the
    rotation by slerp."""
    rotation = slerp(np.array(matrix_to_quaternion(first[:3, :3])), np.array(matrix_to_quaternion(second[:3, :3])),
                     alpha)
    return quaternion_pose(first[:3, 3] + alpha * (second[:3, 3] - first[:3, 3]), rotation)


def axis_angle_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation by ``angle`` radians about the unit vector ``axis`` (Rodrigues' closed form)."""
    cross = np.array(skew_entries(*axis, 0.0))
    return np.eye(3) + math.sin(angle) * cross + (1.0 - math.cos(angle)) * (cross @ cross)


# torch --------------------------------------------------------------------------------------------


def skew(vector: torch.Tensor) -> torch.Tensor:
    """The cross-product matrix of a 3-vector (differentiable)."""
    import torch

    rows = skew_entries(*vector.unbind(), vector.new_zeros(()))
    return torch.stack([torch.stack(row) for row in rows])


def exp_so3(axis_angle: torch.Tensor) -> torch.Tensor:
    """The rotation matrix of an axis-angle 3-vector, exp of its cross-product matrix: differentiable
    also at zero, where Rodrigues' closed form divides by the angle."""
    import torch

    return torch.linalg.matrix_exp(skew(axis_angle))
