"""A step's poses and pose corrections as one batch (``poses.refine``).

Every view of a step renders at its client pose, corrected where it carries a ``PoseCorrection``. One
view at a time, each correction's matrix exponential, prior and gradient step were a hundred-odd
operators a step outside the step's graphs; here the window's poses are one batch, built by one autograd
node whose backward is closed-form (``RefinedPoses``), and every correction that moves takes its step in
one batch too (``corrected``), the prior's gradient folded into it. Neither grows with the window, and the
compiled step holds both as graphs (``ogmapping.mapping.graphs``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from ogmapping.config import PosesConfig
from ogmapping.frames.geometry import world_to_camera
from ogmapping.optim.poses import PoseCorrection, prior_weights

# Below this angle (radians) the left Jacobian's third coefficient, (t - sin t) / t^3, is taken from its
# series: its closed form cancels in float32 there; the series' next term is t^6 / 9!.
SERIES_ANGLE = 0.1


@dataclass(frozen=True)
class Basis:
    """Constants the batch is built from, made once per device and precision (``Basis.on``)."""

    identity: torch.Tensor  # (3, 3)
    skew_index: torch.Tensor  # (9,): the axis component each entry of its cross-product matrix holds...
    skew_sign: torch.Tensor  # (9,): ...and its sign (0 on the diagonal)
    angle_scales: torch.Tensor  # (2,): sinc(angle / pi) = sin(angle) / angle, sinc(angle / 2 pi) for the half angle

    @classmethod
    def on(cls, device: torch.device, dtype: torch.dtype) -> Basis:
        return cls(torch.eye(3, dtype=dtype, device=device),
                   torch.tensor([0, 2, 1, 2, 0, 0, 1, 0, 0], device=device),
                   torch.tensor([0, -1, 1, 1, 0, -1, -1, 1, 0], dtype=dtype, device=device),
                   torch.tensor([1 / math.pi, 0.5 / math.pi], dtype=dtype, device=device))


class RefinedPoses(torch.autograd.Function):
    """The camera-to-worlds ``[exp(r) R | t + dt]`` ``(V, 4, 4)`` of clients' ``c2ws`` ``[R | t]`` corrected by
    ``deltas`` ``(V, 6)`` (dt, then the axis-angle r, in world axes), as ``PoseCorrection.refined`` makes
    them one by one, and their world-to-cameras, the only output with a gradient. The exponential is
    Rodrigues' ``I + A K + B K^2`` (K the cross-product matrix of r, A = sin(t) / t and B = (1 - cos t) / t^2
    at its angle t); r's gradient goes through the exponential's left Jacobian, ``J_l(r)^T w = w - B (r x w)
    + C r x (r x w)`` (C = (t - sin t) / t^3), for the gradient ``w`` of a turn of the corrected rotation
    about the world's axes."""

    @staticmethod
    def forward(ctx, deltas: torch.Tensor, c2ws: torch.Tensor, basis: Basis) -> tuple[torch.Tensor, torch.Tensor]:
        axis = deltas[:, 3:]
        angle = torch.linalg.vector_norm(axis, dim=1, keepdim=True)
        sincs = torch.sinc(angle * basis.angle_scales)  # written to hold at t = 0 too
        first, second = sincs[:, :1], 0.5 * sincs[:, 1:].square()
        cross = (axis[:, basis.skew_index] * basis.skew_sign).unflatten(1, (3, 3))
        rotations = torch.addcmul(torch.bmm(cross * second.unsqueeze(2), cross), first.unsqueeze(2), cross)
        rotated = torch.bmm(rotations + basis.identity, c2ws[:, :3, :3])
        moved = (c2ws[:, :3, 3] + deltas[:, :3]).unsqueeze(2)
        ctx.save_for_backward(axis, angle, first, second, rotated, moved)
        ctx.mark_non_differentiable(c2w := torch.cat([torch.cat([rotated, moved], dim=2), c2ws[:, 3:]], dim=1))
        return c2w, world_to_camera(c2w)  # as a window without corrections inverts its poses, to the last bit

    @staticmethod
    def backward(ctx, _: torch.Tensor, grad: torch.Tensor) -> tuple[torch.Tensor, None, None]:
        axis, angle, first, second, rotated, moved = ctx.saved_tensors
        # The world-to-camera [R^T | -R^T t]'s gradient as the camera-to-world's: R gets G_R^T - t G_u^T, t gets
        # -R G_u, for G_R and G_u its rotation's and translation's.
        towards = grad[:, :3, 3:]
        rotation = torch.baddbmm(grad[:, :3, :3], towards, moved.transpose(1, 2), alpha=-1)  # R's gradient, transposed
        # A turn phi about the world's axes changes the loss by phi . w, w = sum over the columns j of
        # rotated_j x (its gradient)_j (the triple products of <gradient, [phi]x rotated>).
        about = torch.linalg.cross(rotated.transpose(1, 2), rotation, dim=2).sum(1)
        once = torch.linalg.cross(axis, about, dim=1)
        twice = torch.linalg.cross(axis, once, dim=1)
        square = angle.square()  # C's closed form cancels in float32 at small angles: its series there
        third = torch.where(angle < SERIES_ANGLE, 1 / 6 - square / 120 + square.square() / 5040,
                            (1 - first) / square.clamp_min(SERIES_ANGLE**2))
        turned = about - second * once + third * twice
        return torch.cat([torch.bmm(rotated, -towards).squeeze(2), turned], dim=1), None, None


def window_poses(deltas: list[torch.Tensor], c2ws: list[torch.Tensor], basis: Basis) -> tuple[
        tuple[torch.Tensor, ...], tuple[torch.Tensor, ...]]:
    """Each view's corrected pose, without a gradient, and its world-to-camera, differentiable in the
    corrections that move, from each view's correction (zeros for a view without one, detached for one that
    does not move) and its client's pose: one batch."""
    c2w, w2c = RefinedPoses.apply(torch.stack(deltas), torch.stack(c2ws), basis)
    return c2w.unbind(0), w2c.unbind(0)


@dataclass(frozen=True)
class StepRates:
    """What a mapping step's corrections step with, on the device: ``delta <- keep * delta - rates * grad``,
    then each part clamped to its bound. ``keep`` folds in the prior's gradient (``PoseCorrection.prior``:
    2 x weight x delta), so the prior needs no operators in the loss or the backward."""

    keep: torch.Tensor  # (6,)
    rates: torch.Tensor  # (6,)
    bounds: torch.Tensor  # (2,): translation (metres), rotation (radians)

    @classmethod
    def of(cls, settings: PosesConfig, device: torch.device, dtype: torch.dtype) -> StepRates:
        scale = settings.mapping_rate
        rates = torch.tensor([settings.translation_lr * scale] * 3 + [settings.rotation_lr * scale] * 3,
                             dtype=torch.float64)
        weights = torch.tensor(prior_weights(settings), dtype=torch.float64)
        bounds = torch.tensor([settings.max_translation, math.radians(settings.max_rotation)], dtype=torch.float64)
        return cls(*(value.to(device=device, dtype=dtype) for value in (1 - 2 * rates * weights, rates, bounds)))


def corrected(deltas: list[torch.Tensor], grads: list[torch.Tensor], rates: StepRates) -> tuple[
        torch.Tensor, torch.Tensor]:
    """One gradient step of each correction ``deltas`` on its ``grads`` and the prior, clamped: the new 6-vectors
    ``(N, 6)``, and per correction 1 where a part was clamped back to its bound, else 0."""
    stepped = torch.stack(deltas) * rates.keep - torch.stack(grads) * rates.rates
    parts = stepped.unflatten(1, (2, 3))
    norms = torch.linalg.vector_norm(parts, dim=2)
    clamped = (parts * (rates.bounds / norms).clamp(max=1.0).unsqueeze(2)).flatten(1)
    return clamped, (norms > rates.bounds).any(dim=1).to(stepped.dtype)


def step_corrections(corrections: list[PoseCorrection], rates: StepRates, step: Callable = corrected) -> None:
    """One mapping step of every correction in ``corrections`` that has a gradient, as one batch (``step``:
    ``corrected`` or its compiled graph), as ``PoseCorrection.step`` takes one at a time with the prior
    in its loss; the gradients are cleared."""
    moving = [correction for correction in corrections if correction.delta.grad is not None and not correction.held]
    if not moving:
        return
    deltas = [correction.delta for correction in moving]
    stepped, clamped = step(deltas, [delta.grad for delta in deltas], rates)
    with torch.no_grad():
        torch._foreach_copy_(deltas, stepped.unbind(0))
        torch._foreach_maximum_([correction.hit_bound for correction in moving], clamped.unbind(0))
    for correction in moving:
        correction.steps += 1
        correction.delta.grad = None
