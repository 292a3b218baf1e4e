"""A step's poses as one batch: the same poses, world-to-cameras and gradients as the corrections make one
by one through autograd, and the same steps as ``PoseCorrection.step`` with the prior in the loss."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from ogmapping.config import PosesConfig
from ogmapping.frames.geometry import world_to_camera
from ogmapping.frames.rotation import exp_so3
from ogmapping.optim.poses import PoseCorrection
from ogmapping.optim.window_poses import Basis, RefinedPoses, StepRates, corrected, step_corrections, window_poses


def _poses(count: int, generator: torch.Generator, dtype: torch.dtype) -> torch.Tensor:
    """``count`` random rigid camera-to-worlds."""
    poses = torch.eye(4, dtype=torch.float64).repeat(count, 1, 1)
    poses[:, :3, :3] = torch.stack([exp_so3(torch.randn(3, generator=generator, dtype=torch.float64))
                                    for _ in range(count)])
    poses[:, :3, 3] = torch.randn(count, 3, generator=generator, dtype=torch.float64) * 2
    return poses.to(dtype)


def _deltas(generator: torch.Generator, dtype: torch.dtype) -> torch.Tensor:
    """Corrections from none through tiny (the series' side of ``SERIES_ANGLE``) to a third of a turn."""
    deltas = torch.randn(6, 6, generator=generator, dtype=torch.float64) * 0.05
    deltas[0] = 0.0
    deltas[1, 3:] *= 1e-4
    deltas[2, 3:] = deltas[2, 3:] / deltas[2, 3:].norm() * 0.0999
    deltas[3, 3:] = deltas[3, 3:] / deltas[3, 3:].norm() * 0.1001
    deltas[4, 3:] = deltas[4, 3:] / deltas[4, 3:].norm() * 2.0
    return deltas.to(dtype)


def _reference(deltas: torch.Tensor, c2ws: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """What the batch replaces: each correction's ``refined`` pose through autograd, and its inverse."""
    refined = []
    for delta, c2w in zip(deltas, c2ws, strict=True):
        correction = PoseCorrection("cpu", c2w.dtype)
        correction.delta = delta
        refined.append(correction.refined(c2w))
    poses = torch.stack(refined)
    return poses, world_to_camera(poses)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_batch_gives_each_correction_its_pose_and_gradient(dtype):
    generator = torch.Generator().manual_seed(5)
    c2ws = _poses(6, generator, dtype)
    deltas = _deltas(generator, dtype)
    weights = torch.randn(6, 4, 4, generator=generator, dtype=torch.float64).to(dtype)
    ours = deltas.clone().requires_grad_(True)
    c2w, w2c = RefinedPoses.apply(ours, c2ws, Basis.on(torch.device("cpu"), dtype))
    (w2c * weights).sum().backward()
    theirs = deltas.clone().requires_grad_(True)
    expected_c2w, expected_w2c = _reference(theirs, c2ws)
    (expected_w2c * weights).sum().backward()
    tolerance = {"rtol": 1e-10, "atol": 1e-12} if dtype == torch.float64 else {"rtol": 2e-5, "atol": 2e-6}
    torch.testing.assert_close(c2w, expected_c2w.detach(), **tolerance)
    torch.testing.assert_close(w2c, expected_w2c.detach(), **tolerance)
    torch.testing.assert_close(ours.grad, theirs.grad, **tolerance)
    assert not c2w.requires_grad  # the poses a step decodes from carry no gradient


def test_the_batch_passes_torchs_gradient_check():
    generator = torch.Generator().manual_seed(7)
    c2ws = _poses(6, generator, torch.float64)
    deltas = _deltas(generator, torch.float64).requires_grad_(True)
    basis = Basis.on(torch.device("cpu"), torch.float64)
    assert torch.autograd.gradcheck(lambda d: RefinedPoses.apply(d, c2ws, basis)[1], (deltas,))


def test_a_view_without_a_moving_correction_keeps_its_pose_to_the_last_bit():
    generator = torch.Generator().manual_seed(11)
    c2ws = list(_poses(3, generator, torch.float32))
    zeros = torch.zeros(6)
    poses, viewmats = window_poses([zeros, zeros, zeros], c2ws, Basis.on(torch.device("cpu"), torch.float32))
    plain = world_to_camera(torch.stack(c2ws))
    for pose, viewmat, c2w, expected in zip(poses, viewmats, c2ws, plain, strict=True):
        assert torch.equal(pose, c2w) and torch.equal(viewmat, expected)


def _stepped_one_by_one(deltas: torch.Tensor, grads: torch.Tensor, settings: PosesConfig) -> list[PoseCorrection]:
    """``PoseCorrection.step`` on each, the prior's gradient in its gradient, at the mapping steps' rates."""
    scaled = dataclasses.replace(settings, translation_lr=settings.translation_lr * settings.mapping_rate,
                                 rotation_lr=settings.rotation_lr * settings.mapping_rate)
    corrections = []
    for delta, grad in zip(deltas, grads, strict=True):
        correction = PoseCorrection("cpu", torch.float64)
        with torch.no_grad():
            correction.delta.copy_(delta)
        correction.prior(scaled).backward()
        correction.delta.grad += grad
        correction.step(scaled)
        corrections.append(correction)
    return corrections


def test_a_batched_step_is_each_corrections_step_with_its_prior_and_clamps_as_it():
    settings = PosesConfig(mapping_rate=0.25, prior=0.3, max_translation=0.05, max_rotation=3.0)
    generator = torch.Generator().manual_seed(13)
    deltas = torch.randn(4, 6, generator=generator, dtype=torch.float64) * 0.01
    grads = torch.randn(4, 6, generator=generator, dtype=torch.float64)
    grads[2, :3] = torch.tensor([-40.0, 0.0, 0.0])  # runs past the translation's bound
    grads[3, 3:] = torch.tensor([0.0, 0.0, -300.0])  # and this one past the rotation's
    corrections = []
    for delta, grad in zip(deltas, grads, strict=True):
        correction = PoseCorrection("cpu", torch.float64)
        with torch.no_grad():
            correction.delta.copy_(delta)
        correction.delta.grad = grad.clone()
        corrections.append(correction)
    held = PoseCorrection("cpu", torch.float64)
    held.hold()
    step_corrections([*corrections, held, PoseCorrection("cpu", torch.float64)],
                     StepRates.of(settings, torch.device("cpu"), torch.float64))
    expected = _stepped_one_by_one(deltas, grads, settings)
    for ours, theirs in zip(corrections, expected, strict=True):
        torch.testing.assert_close(ours.delta.detach(), theirs.delta.detach(), rtol=1e-12, atol=1e-15)
        assert ours.steps == theirs.steps == 1 and ours.delta.grad is None
        assert ours.clamped == theirs.clamped
    assert [correction.clamped for correction in corrections] == [False, False, True, True]
    assert float(corrections[2].translation.norm()) == pytest.approx(0.05)
    assert float(corrections[3].rotation.norm()) == pytest.approx(math.radians(3.0))
    assert held.steps == 0 and not held.delta.detach().any()


def test_a_clamped_correction_stays_reported_as_clamped():
    settings = PosesConfig(max_translation=0.01)
    correction = PoseCorrection("cpu")
    rates = StepRates.of(settings, torch.device("cpu"), torch.float32)
    correction.delta.grad = torch.tensor([-10.0, 0, 0, 0, 0, 0])
    step_corrections([correction], rates)
    correction.delta.grad = torch.tensor([1.0, 0, 0, 0, 0, 0])  # back inside the bound
    step_corrections([correction], rates)
    assert correction.clamped and correction.steps == 2


def test_the_step_is_the_same_compiled():
    settings = PosesConfig(mapping_rate=0.5, max_translation=0.02)
    generator = torch.Generator().manual_seed(17)
    deltas = list(torch.randn(3, 6, generator=generator) * 0.01)
    grads = list(torch.randn(3, 6, generator=generator) * 4)
    rates = StepRates.of(settings, torch.device("cpu"), torch.float32)
    compiled = torch.compile(corrected, fullgraph=True)
    for ours, theirs in zip(compiled(deltas, grads, rates), corrected(deltas, grads, rates), strict=True):
        torch.testing.assert_close(ours, theirs)


def test_the_poses_are_the_same_compiled_values_and_gradients():
    generator = torch.Generator().manual_seed(19)
    c2ws = list(_poses(3, generator, torch.float32))
    basis = Basis.on(torch.device("cpu"), torch.float32)
    weights = torch.randn(3, 4, 4, generator=generator)
    corrections = _deltas(generator, torch.float32)[2:5]  # the series' side, its edge, a large turn
    results = []
    for run in (window_poses, torch.compile(window_poses, fullgraph=True)):
        deltas = [delta.clone().requires_grad_(True) for delta in corrections]
        poses, viewmats = run(deltas, c2ws, basis)
        (torch.stack(viewmats) * weights).sum().backward()
        results.append((torch.stack(poses), torch.stack(viewmats), torch.stack([delta.grad for delta in deltas])))
    for ours, theirs in zip(*results, strict=True):
        torch.testing.assert_close(ours, theirs)
