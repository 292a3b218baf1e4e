"""The rotation module: quaternions, axis-angle and the matrix exponential, numpy and torch held to each other.

Known rotations, round trips (seeded and drawn by hypothesis), Rodrigues' closed form as the reference
for the quaternion formulas and for torch's matrix exponential, and the float operations pinned.
"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from ogmapping.frames.rotation import (
    axis_angle_matrix,
    exp_so3,
    matrix_to_quaternion,
    quaternion_entries,
    quaternion_pose,
    quaternion_to_matrix,
    skew,
    slerp,
)

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

COMPONENT = st.floats(-1.0, 1.0, allow_nan=False, allow_infinity=False)
# Quaternions away from zero (a zero quaternion is no rotation), in (x, y, z, w) order.
QUATERNIONS = st.tuples(COMPONENT, COMPONENT, COMPONENT, COMPONENT).filter(lambda q: np.linalg.norm(q) > 1e-3)
AXIS_ANGLES = st.tuples(COMPONENT, COMPONENT, COMPONENT).map(lambda v: 3.0 * np.array(v))


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


def test_axis_angle_known_turns() -> None:
    np.testing.assert_allclose(axis_angle_matrix(np.array([0.0, 0.0, 1.0]), np.pi / 2), KNOWN[3][1], atol=1e-15)
    np.testing.assert_allclose(axis_angle_matrix(np.array([1.0, 0.0, 0.0]), np.pi), KNOWN[4][1], atol=1e-15)
    np.testing.assert_array_equal(axis_angle_matrix(np.array([0.0, 1.0, 0.0]), 0.0), np.eye(3))


def test_quaternion_pose() -> None:
    pose = quaternion_pose(np.array([1.0, -2.0, 0.5]), (0.0, 0.0, S, S))
    np.testing.assert_array_equal(pose[:3, :3], quaternion_to_matrix(0.0, 0.0, S, S))
    np.testing.assert_array_equal(pose[:3, 3], [1.0, -2.0, 0.5])
    np.testing.assert_array_equal(pose[3], [0.0, 0.0, 0.0, 1.0])


@settings(max_examples=200, deadline=None)
@given(QUATERNIONS)
def test_quaternion_round_trip(q: tuple[float, float, float, float]) -> None:
    unit = np.array(q) / np.linalg.norm(q)
    matrix = quaternion_to_matrix(*q)
    np.testing.assert_allclose(matrix @ matrix.T, np.eye(3), atol=1e-14)
    assert np.linalg.det(matrix) == pytest.approx(1.0)
    back = np.array(matrix_to_quaternion(matrix))
    assert same_rotation(back, unit)
    np.testing.assert_allclose(quaternion_to_matrix(*back), matrix, atol=1e-14)


@settings(max_examples=200, deadline=None)
@given(AXIS_ANGLES)
def test_axis_angle_agrees_with_its_quaternion(vector: np.ndarray) -> None:
    angle = float(np.linalg.norm(vector))
    if angle < 1e-6:
        return
    axis = vector / angle
    q = np.array([*(np.sin(angle / 2) * axis), np.cos(angle / 2)])
    np.testing.assert_allclose(axis_angle_matrix(axis, angle), quaternion_to_matrix(*q), atol=1e-14)
    np.testing.assert_allclose(axis_angle_matrix(axis, angle) @ axis, axis, atol=1e-14)  # the axis stays put


# numpy and torch ----------------------------------------------------------------------------------


@settings(max_examples=100, deadline=None)
@given(QUATERNIONS)
def test_one_quaternion_formula_for_numpy_and_torch(q: tuple[float, float, float, float]) -> None:
    """The same float operations on numpy scalars and on float64 tensors: equal to the bit."""
    x, y, z, w = np.array(q) / np.linalg.norm(q)
    on_numpy = np.array(quaternion_entries(w, x, y, z))
    components = torch.tensor([w, x, y, z], dtype=torch.float64).unbind()
    on_torch = torch.stack([torch.stack(row) for row in quaternion_entries(*components)])
    np.testing.assert_array_equal(on_torch.numpy(), on_numpy)
    np.testing.assert_allclose(on_numpy, quaternion_to_matrix(x, y, z, w), atol=1e-15)  # renormalised there


def test_quaternion_entries_of_a_batch_carry_gradients() -> None:
    """Renderer use: (N,) tensors per component, differentiable; each entry matches the numpy matrix."""
    quats = torch.randn(64, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0)).requires_grad_(True)
    unit = torch.nn.functional.normalize(quats, dim=-1)
    entries = quaternion_entries(*unit.unbind(-1))
    matrices = torch.stack([torch.stack(row, -1) for row in entries], -2)
    for quaternion, matrix in zip(quats.detach().numpy(), matrices.detach().numpy(), strict=True):
        w, x, y, z = quaternion
        np.testing.assert_allclose(matrix, quaternion_to_matrix(x, y, z, w), atol=1e-15)
    matrices.sum().backward()
    assert quats.grad is not None and torch.isfinite(quats.grad).all()


@settings(max_examples=100, deadline=None)
@given(AXIS_ANGLES, st.tuples(COMPONENT, COMPONENT, COMPONENT))
def test_skew_is_the_cross_product(vector: np.ndarray, other: tuple[float, float, float]) -> None:
    np.testing.assert_allclose(skew(torch.from_numpy(vector)).numpy() @ other, np.cross(vector, other), atol=1e-15)


@settings(max_examples=100, deadline=None)
@given(AXIS_ANGLES)
def test_torch_exponential_is_numpy_rodrigues(vector: np.ndarray) -> None:
    angle = float(np.linalg.norm(vector))
    expected = np.eye(3) if angle == 0.0 else axis_angle_matrix(vector / angle, angle)
    np.testing.assert_allclose(exp_so3(torch.from_numpy(vector)).numpy(), expected, atol=1e-12)
    quaternion = matrix_to_quaternion(exp_so3(torch.from_numpy(vector)).numpy())
    np.testing.assert_allclose(quaternion_to_matrix(*quaternion), expected, atol=1e-12)


def test_torch_exponential_is_differentiable_at_zero() -> None:
    zero = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    exp_so3(zero)[0, 1].backward()
    assert torch.allclose(zero.grad, torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64))


def test_torch_exponential_gradient_matches_finite_differences() -> None:
    vector = torch.tensor([0.3, -0.7, 0.2], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(exp_so3, (vector,))
