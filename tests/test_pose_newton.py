"""Gauss-Newton tracking: the residuals it steps on, its Jacobian against autograd, and its steps."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from test_poses import _pixel_shift

from ogmapping.config import LossConfig, PosesConfig, resolve
from ogmapping.frames.preprocess import prepare
from ogmapping.mapper import Mapper
from ogmapping.optim.losses import tracking_loss, tracking_mask, tracking_residuals
from ogmapping.optim.pose_newton import jacobian, newton_track
from ogmapping.optim.poses import PoseCorrection
from ogmapping.quality.evaluation import open_frames

SHIFT = np.array([0.008, -0.006, 0.004])  # metres: the displaced frame's error


def test_tracking_residuals_sum_to_the_tracking_loss():
    generator = torch.Generator().manual_seed(3)
    height, width = 7, 9
    render_color, gt_color = torch.rand(2, height, width, 3, generator=generator).unbind()
    render_depth = torch.rand(height, width, generator=generator) + 1
    gt_depth = torch.rand(height, width, generator=generator) + 1
    gt_depth[0, :4] = 0.0
    gt_depth[1, 2] = float("nan")
    alpha = torch.rand(height, width, generator=generator)
    alpha[2:5] = 0.995
    weights = LossConfig(color=0.7, depth=1.3)
    mask = tracking_mask(alpha, gt_depth, 0.99)
    residuals = tracking_residuals(render_color, render_depth, gt_color, gt_depth, weights, mask)
    expected = tracking_loss(render_color, render_depth, alpha, gt_color, gt_depth, weights, 0.99)
    assert residuals.shape == (height * width * 4,)
    assert float(residuals.abs().sum()) == pytest.approx(float(expected), rel=1e-6)
    outside = ~mask.covered
    assert not residuals[: height * width * 3].reshape(height, width, 3)[outside].any()


@pytest.fixture(scope="module")
def tracked() -> tuple[Mapper, object, np.ndarray]:
    """A small map of synthetic frames, made at their exact poses, and the last of them, prepared, at a pose
    ``SHIFT`` off its truth: the map has seen that frame there, so its tracking loss is lowest near the truth.
    Thirty steps a keyframe: with the preset's ten, where that lowest loss lies moves by up to a pixel with the
    map's last bits (seeds). Made without refinement, so no keyframe's correction moves the map off the truth."""
    frames = open_frames("synthetic", "synthetic", "0:7", 1, 1.0, n_frames=40)  # 320x240
    loaded = [frames.load(position) for position in range(7)]
    mapper = Mapper(resolve("sparse", overrides={"keyframes.frame_iterations": "6", "keyframes.iterations": "30"}))
    for frame in loaded:
        mapper.process(frame)
    truth = np.asarray(loaded[6].c2w, dtype=np.float64)
    given = truth.copy()
    given[:3, 3] += SHIFT
    octree = mapper.config.octree
    return mapper, prepare(dataclasses.replace(loaded[6], c2w=given), octree.depth_min, octree.depth_max), truth


def test_the_difference_jacobian_gives_the_losss_autograd_gradient(tracked):
    mapper, frame, _ = tracked
    delta = torch.tensor([0.002, -0.001, 0.001, 0.001, -0.002, 0.0005])
    correction = PoseCorrection(mapper.device)
    with torch.no_grad():
        correction.delta.copy_(delta)
    with mapper.lock:
        mapper.tracker.objective(frame)(correction).backward()
        residuals_at = mapper.tracker.residuals(frame)
        residuals, mask = residuals_at(delta, None)
        difference = jacobian(residuals_at, delta, residuals, mask).T @ torch.sign(residuals)
    autograd = correction.delta.grad
    cosine = float(torch.nn.functional.cosine_similarity(difference, autograd, dim=0))
    assert cosine > 0.97, (difference, autograd)
    assert float(difference.norm() / autograd.norm()) == pytest.approx(1.0, abs=0.25)  # the L1 has kinks


def test_newton_steps_lower_the_loss_and_take_the_pose_towards_the_truth(tracked):
    mapper, frame, truth = tracked
    settings = PosesConfig()
    correction = PoseCorrection(mapper.device)
    with mapper.lock:
        loss_at = mapper.tracker.objective(frame)
        with torch.no_grad():
            before = float(loss_at(correction))
        done = newton_track(mapper.tracker.residuals(frame), correction, settings, 3, lambda: False)
        with torch.no_grad():
            after = float(loss_at(correction))
    assert done.steps >= 1 and done.renders >= 1 + 7 * done.steps
    assert after < before
    refined = correction.refined(torch.as_tensor(frame.c2w, dtype=torch.float32)).detach().double().numpy()
    before_shift = _pixel_shift(frame, truth, frame.c2w)
    assert before_shift > 0.5, before_shift
    assert _pixel_shift(frame, truth, refined) < 0.75 * before_shift
    assert correction.steps == done.steps and not correction.clamped


def test_newton_track_leaves_a_held_pose_alone_and_stops_when_told(tracked):
    mapper, frame, _ = tracked
    held = PoseCorrection(mapper.device)
    held.hold()
    with mapper.lock:
        residuals_at = mapper.tracker.residuals(frame)
        assert newton_track(residuals_at, held, PosesConfig(), 3, lambda: False).renders == 0
        stopped = PoseCorrection(mapper.device)
        done = newton_track(residuals_at, stopped, PosesConfig(), 3, lambda: True)
    assert (done.steps, done.renders) == (0, 1) and not stopped.delta.detach().any()


def test_a_newton_step_past_the_bound_is_clamped_and_reported(tracked):
    mapper, frame, _ = tracked
    settings = PosesConfig(max_translation=0.001, prior=0.0)
    correction = PoseCorrection(mapper.device)
    with mapper.lock:
        newton_track(mapper.tracker.residuals(frame), correction, settings, 2, lambda: False)
    assert correction.clamped
    assert float(correction.translation.detach().norm()) == pytest.approx(0.001, rel=1e-5)


@pytest.mark.parametrize("residual", [1.0, float("nan")], ids=["unobservable", "not-finite"])
def test_a_singular_system_skips_the_step_and_fails_nothing(residual):
    """A pose the residuals do not depend on (a view of nothing), with no prior, gives a singular normal
    matrix; residuals that are not finite give one of NaNs. Either way the correction stays put."""
    mask = tracking_mask(torch.ones(4, 5), torch.ones(4, 5), 0.5)

    def residuals_at(delta, given):
        return torch.full((40,), residual), given if given is not None else mask

    correction = PoseCorrection("cpu")
    settings = PosesConfig(max_translation=1e6, max_rotation=180.0, prior=0.0, translation_lr=1.0, rotation_lr=1.0)
    done = newton_track(residuals_at, correction, settings, 3, lambda: False)
    assert done.steps == 0 and not correction.delta.detach().any()
