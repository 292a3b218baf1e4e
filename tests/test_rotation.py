"""Quaternion <-> matrix conversions and slerp: known rotations, round trips, an independent reference."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from ogmapping.frames.rotation import matrix_to_quaternion, quaternion_to_matrix, slerp

# 90 degrees about x, y and z, and the half-turns that take the three non-trace branches.
S = np.sqrt(0.5)
KNOWN = [
    ((0.0, 0.0, 0.0, 1.0), np.eye(3)),
    ((S, 0.0, 0.0, S), np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])),
    ((0.0, S, 0.0, S), np.array([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]])),
    ((0.0, 0.0, S, S), np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])),
    ((1.0, 0.0, 0.0, 0.0), np.diag([1.0, -1.0, -1.0])),
    ((0.0, 1.0, 0.0, 0.0), np.diag([-1.0, 1.0, -1.0])),
    ((0.0, 0.0, 1.0, 0.0), np.diag([-1.0, -1.0, 1.0])),
]


def axis_angle_matrix(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues' formula: the reference, written without quaternions."""
    k = np.array([[0.0, -axis[2], axis[1]], [axis[2], 0.0, -axis[0]], [-axis[1], axis[0], 0.0]])
    return np.eye(3) + np.sin(angle) * k + (1.0 - np.cos(angle)) * (k @ k)


def random_axis_angles(count: int, seed: int) -> list[tuple[np.ndarray, float]]:
    rng = np.random.default_rng(seed)
    axes = rng.normal(size=(count, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    return list(zip(axes, rng.uniform(-np.pi, np.pi, count), strict=True))


def same_rotation(q: np.ndarray, expected: np.ndarray) -> bool:
    """q and -q are the same rotation."""
    return bool(np.allclose(q, expected, atol=1e-12) or np.allclose(q, -expected, atol=1e-12))


@pytest.mark.parametrize(("quaternion", "matrix"), KNOWN)
def test_known_rotations(quaternion: tuple[float, ...], matrix: np.ndarray) -> None:
    np.testing.assert_allclose(quaternion_to_matrix(*quaternion), matrix, atol=1e-15)
    assert same_rotation(np.array(matrix_to_quaternion(matrix)), np.array(quaternion))


def test_quaternion_to_matrix_normalises() -> None:
    np.testing.assert_allclose(quaternion_to_matrix(0.2, -0.6, 0.4, 1.8), quaternion_to_matrix(0.1, -0.3, 0.2, 0.9),
                               atol=1e-15)


def test_equal_to_axis_angle_reference_on_random_rotations() -> None:
    for axis, angle in random_axis_angles(500, seed=0):
        expected_q = np.array([*(np.sin(angle / 2) * axis), np.cos(angle / 2)])
        reference = axis_angle_matrix(axis, angle)
        matrix = quaternion_to_matrix(*expected_q)
        np.testing.assert_allclose(matrix, reference, atol=1e-14)
        np.testing.assert_allclose(matrix @ matrix.T, np.eye(3), atol=1e-14)
        assert np.linalg.det(matrix) == pytest.approx(1.0)
        assert same_rotation(np.array(matrix_to_quaternion(reference)), expected_q)


def test_round_trips() -> None:
    for axis, angle in random_axis_angles(500, seed=1):
        matrix = axis_angle_matrix(axis, angle)
        q = matrix_to_quaternion(matrix)
        assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-15)
        np.testing.assert_allclose(quaternion_to_matrix(*q), matrix, atol=1e-14)
        assert same_rotation(np.array(matrix_to_quaternion(quaternion_to_matrix(*q))), np.array(q))


def test_matrix_to_quaternion_is_pinned_bit_for_bit() -> None:
    """Recordings hold these quaternions: the float operations must not change. Only +, -, *, / and
    sqrt are involved (correctly rounded everywhere), over matrices that take all four branches."""
    matrices = np.random.default_rng(2).normal(size=(4000, 3, 3))
    traces = np.trace(matrices, axis1=1, axis2=2)
    assert (traces > 0).any() and (traces <= 0).any()
    digest = hashlib.sha256(np.array([matrix_to_quaternion(m) for m in matrices]).tobytes()).hexdigest()
    assert digest == "6bade866e8c372bccd13898294b583c9bd9bea8ad7cea49c50cee488a0074a24"


def test_slerp() -> None:
    q0 = np.array([0.0, 0.0, 0.0, 1.0])
    q1 = np.array([0.0, 0.0, np.sin(0.6), np.cos(0.6)])  # 1.2 rad about z
    np.testing.assert_allclose(slerp(q0, q1, 0.0), q0, atol=1e-15)
    np.testing.assert_allclose(slerp(q0, q1, 1.0), q1, atol=1e-15)
    np.testing.assert_allclose(slerp(q0, q1, 0.25), [0.0, 0.0, np.sin(0.15), np.cos(0.15)], atol=1e-15)
    np.testing.assert_allclose(slerp(q0, -q1, 0.25), [0.0, 0.0, np.sin(0.15), np.cos(0.15)], atol=1e-15)
    near = np.array([0.0, 0.0, np.sin(1e-3), np.cos(1e-3)])
    np.testing.assert_allclose(slerp(q0, near, 0.5), [0.0, 0.0, np.sin(5e-4), np.cos(5e-4)], atol=1e-12)
