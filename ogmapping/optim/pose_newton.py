"""Gauss-Newton tracking steps on one pose correction (``poses.track_newton_iterations``).

The tracking loss is nearly flat along the camera's translation, so gradient steps at a fixed rate
approach the truth slowly there (bench/RESULTS.md, "What bounds tracking"). A Gauss-Newton step uses
the loss's curvature instead: it solves for the correction that best explains every pixel's residual
at once, as SLAM systems track. The loss is an L1, so each step is one of iteratively reweighted least
squares: a residual ``r`` weighs ``1 / max(|r|, WEIGHT_FLOOR * mean |r|)`` in the normal equations,
whose right-hand side is then exactly the L1's gradient. The Jacobian of the residuals with respect to
the six correction coordinates comes from finite differences of renders, so it needs no backward pass
and works on every backend: a step costs seven forward renders. Levenberg-Marquardt damping keeps a
step that would raise the loss (prior included) from being taken: it is retried with more damping,
and the correction stays where it was if none of ``TRIES`` lowers the loss. A system with no solution
(a coordinate the residuals do not depend on and no prior to hold it, or residuals that are not
finite) counts as such a try: the step is skipped, the frame goes on.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from ogmapping.config import PosesConfig
from ogmapping.optim.losses import TrackingMask
from ogmapping.optim.poses import PoseCorrection

# Finite-difference steps: metres for the translation, radians for the rotation (about 0.02 degrees).
DIFFERENCE_STEP = (1e-3, 3e-4)
# Residuals smaller than this multiple of the mean |residual| weigh as much as one of that size: near
# zero the reweighting of the L1 would otherwise let a few well-fitted pixels dwarf the rest.
WEIGHT_FLOOR = 3.0
DAMPING_START = 0.01  # Levenberg-Marquardt: times the normal matrix's diagonal
DAMPING_FALL = 3.0  # divided by this after a step that lowered the loss
DAMPING_RISE = 4.0  # multiplied by this after one that did not (from at least DAMPING_FLOOR)
DAMPING_FLOOR = 1e-3
TRIES = 3  # damped solves per step before the step is given up


# delta (6,), mask (None: decide it from this render) -> (residuals, the mask they were taken over)
Residuals = Callable[[torch.Tensor, TrackingMask | None], tuple[torch.Tensor, TrackingMask]]


@dataclass
class NewtonTracking:
    """What Gauss-Newton tracking did to one pose: steps taken and renders spent."""

    steps: int = 0
    renders: int = 0


def objective(residuals: torch.Tensor, delta: torch.Tensor, prior_weights: torch.Tensor) -> float:
    """The tracking loss (sum of |residual|) plus the prior, as one number."""
    return float(residuals.abs().sum() + (prior_weights * delta * delta).sum())


def jacobian(residuals_at: Residuals, delta: torch.Tensor, base: torch.Tensor, mask: TrackingMask) -> torch.Tensor:
    """(n, 6) derivatives of the residuals with respect to delta, by forward differences over ``mask``."""
    columns = []
    for index in range(6):
        step = DIFFERENCE_STEP[0] if index < 3 else DIFFERENCE_STEP[1]
        moved = delta.clone()
        moved[index] += step
        columns.append((residuals_at(moved, mask)[0] - base) / step)
    return torch.stack(columns, dim=1)


def normal_equations(jac: torch.Tensor, residuals: torch.Tensor, delta: torch.Tensor,
                     prior_weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The reweighted normal matrix and the gradient (of the L1 plus the prior), in float64."""
    size = residuals.abs()
    counted = size > 0  # pixels outside the mask have residual 0 and no weight
    floor = WEIGHT_FLOOR * size[counted].mean() if bool(counted.any()) else size.new_tensor(1.0)
    weights = torch.where(counted, 1.0 / size.clamp_min(floor), 0.0)
    normal = jac.T @ (weights.unsqueeze(1) * jac) + torch.diag(2 * prior_weights)
    gradient = jac.T @ torch.sign(residuals) + 2 * prior_weights * delta
    return normal.double(), gradient.double()


def newton_track(residuals_at: Residuals, correction: PoseCorrection, settings: PosesConfig, iterations: int,
                 stop: Callable[[], bool]) -> NewtonTracking:
    """Up to ``iterations`` damped Gauss-Newton steps on ``correction`` (not one held), until ``stop()``."""
    done = NewtonTracking()
    if correction.held or iterations <= 0:
        return done
    prior_weights = correction.prior_weights(settings)
    delta = correction.delta.detach().clone()
    residuals, mask = residuals_at(delta, None)
    done.renders += 1
    loss = objective(residuals, delta, prior_weights)
    damping = DAMPING_START
    for _ in range(iterations):
        if stop():
            break
        normal, gradient = normal_equations(jacobian(residuals_at, delta, residuals, mask), residuals, delta,
                                            prior_weights)
        done.renders += 6
        moved = False
        for _ in range(TRIES):
            damped = normal + damping * torch.diag(torch.diag(normal))
            solution, info = torch.linalg.solve_ex(damped, gradient)
            if int(info) != 0 or not bool(torch.isfinite(solution).all()):  # singular: a coordinate unseen
                damping = max(damping * DAMPING_RISE, DAMPING_FLOOR)
                continue
            candidate = delta - solution.to(delta.dtype)
            candidate_residuals, candidate_mask = residuals_at(candidate, None)
            done.renders += 1
            candidate_loss = objective(candidate_residuals, candidate, prior_weights)
            if candidate_loss < loss:
                delta, residuals, mask, loss = candidate, candidate_residuals, candidate_mask, candidate_loss
                damping /= DAMPING_FALL
                moved = True
                break
            damping = max(damping * DAMPING_RISE, DAMPING_FLOOR)
        if not moved:
            break
        correction.move_to(delta, settings)
        done.steps += 1
        if not torch.equal(correction.delta.detach(), delta):  # clamped back to a bound: start from there
            delta = correction.delta.detach().clone()
            residuals, mask = residuals_at(delta, None)
            done.renders += 1
            loss = objective(residuals, delta, prior_weights)
    return done
