"""Pose refinement: a learnable SE(3) correction of a client's camera pose (``poses.refine``).

Clients send the poses they have (odometry, ARKit, KinectFusion), none exact. Each keyframe but
the first, and the streamed view, carries a ``PoseCorrection``: a translation of the camera centre
and a rotation about it, both in world axes, so the refined camera-to-world is
``[exp(r) R | t + dt]`` for the client's ``[R | t]``. It is optimised with the map in the same
steps, by gradient descent at its own rates (``poses.translation_lr`` / ``rotation_lr``), under a
prior that holds it near the client's pose; a correction beyond ``poses.max_translation`` /
``max_rotation`` is clamped back to the bound and reported as clamped.

The first keyframe has none, so the map stays in the client's frame. The rasterizer gives the
gradient of the loss with respect to each view's world-to-camera matrix (every backend), which
autograd carries to the correction through ``refined``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ogmapping.config import PosesConfig
from ogmapping.frames.rotation import exp_so3
from ogmapping.runtime.host_read import read

STATE_SIZE = 9  # a correction's checkpoint row: delta (6), steps, clamped, held
STATE_SIZES = (8, STATE_SIZE)  # rows written before ``held`` lack it


@dataclass(frozen=True)
class PoseReport:
    """A frame's correction as results report it: world-axis translation of the camera centre
    (metres), rotation about it (axis-angle, radians), whether it hit the bound, and the pose."""

    translation: np.ndarray  # (3,)
    rotation: np.ndarray  # (3,)
    clamped: bool
    refined_c2w: np.ndarray  # (4, 4)

    @property
    def translation_m(self) -> float:
        return float(np.linalg.norm(self.translation))

    @property
    def rotation_deg(self) -> float:
        return math.degrees(float(np.linalg.norm(self.rotation)))

    @classmethod
    def unrefined(cls, c2w: np.ndarray) -> PoseReport:
        return cls(np.zeros(3), np.zeros(3), False, np.asarray(c2w, dtype=np.float64))


TRACK_CHECK_STEPS = 2  # tracking steps after which ``settled`` decides whether a pose moves at all


def settled(losses: list[torch.Tensor], min_gain: float) -> bool:
    """Whether tracking's second step lowered the loss by less than ``min_gain`` of the first loss
    (``losses``: before the first step, before the second, after it). A right pose's loss falls on the
    first step as the pose fits the young map's own error, and then stops; a wrong pose's keeps
    falling (bench/RESULTS.md, "Pose refinement"). Never with ``min_gain`` 0, not even where the loss rose."""
    if min_gain <= 0:
        return False
    first, before, after = read(*losses[:TRACK_CHECK_STEPS + 1])  # one read from the device
    return (before - after) < min_gain * max(first, 1e-12)


def prior_weights(settings: PosesConfig) -> list[float]:
    """The six weights of ``PoseCorrection.prior`` as ``sum(weights * delta**2)``: translation's, then rotation's."""
    translation = settings.prior / settings.max_translation**2
    rotation = settings.prior / math.radians(settings.max_rotation) ** 2
    return [translation] * 3 + [rotation] * 3


class PoseCorrection:
    """One pose's correction (translation, then axis-angle rotation, as one leaf 6-vector), stepped
    on its own, so corrections come and go with keyframes without touching the map's optimiser."""

    def __init__(self, device: torch.device | str, dtype: torch.dtype = torch.float32) -> None:
        self.delta = torch.zeros(6, device=device, dtype=dtype, requires_grad=True)
        self.steps = 0
        # 1 once it hit the bound at some step, else 0: kept on the device, so a step never waits to learn it
        # (``clamped`` reads it; a mapping step's batch raises it, ``ogmapping.optim.window_poses``).
        self.hit_bound = torch.zeros((), dtype=dtype, device=device)
        self.held = False  # kept at the client's pose for good (``hold``)

    @property
    def clamped(self) -> bool:
        return bool(self.hit_bound)

    @clamped.setter
    def clamped(self, value: bool) -> None:
        self.hit_bound.fill_(float(value))

    @property
    def translation(self) -> torch.Tensor:
        return self.delta[:3]

    @property
    def rotation(self) -> torch.Tensor:
        return self.delta[3:]

    def refined(self, c2w: torch.Tensor) -> torch.Tensor:
        """The corrected camera-to-world of the client's ``c2w``, differentiable in ``delta``."""
        delta = self.delta.to(c2w.dtype)
        rotation = exp_so3(delta[3:]) @ c2w[:3, :3]
        top = torch.cat([rotation, (c2w[:3, 3] + delta[:3]).unsqueeze(1)], dim=1)
        return torch.cat([top, c2w[3:]], dim=0)

    def prior(self, settings: PosesConfig) -> torch.Tensor:
        """The cost of straying from the client's pose, ``poses.prior`` at the bound."""
        scale = math.radians(settings.max_rotation)
        return settings.prior * (self.translation.square().sum() / settings.max_translation**2
                                 + self.rotation.square().sum() / scale**2)

    def prior_weights(self, settings: PosesConfig) -> torch.Tensor:
        """The prior as ``sum(weights * delta**2)``: its six weights."""
        return self.delta.new_tensor(prior_weights(settings))

    def hold(self) -> None:
        """Back to the client's pose, to stay there: its tracking ``settled`` (``poses.track_min_gain``),
        and steps that move it anyway fit the young map's errors instead."""
        with torch.no_grad():
            self.delta.zero_()
        self.delta.grad = None
        self.held = True

    def step(self, settings: PosesConfig) -> None:
        """One gradient step on ``delta`` (none without a gradient), then clamp to the bounds.

        Plain gradient descent, not Adam: Adam's first step moves every coordinate by its learning
        rate whatever the gradient's size, so a pose that is already right takes a step the size of the
        noise it was meant to remove; here a small gradient (a pose near its optimum) makes a small step.
        """
        grad = self.delta.grad
        if grad is None or self.held:
            return
        self.steps += 1
        with torch.no_grad():
            rates = self.delta.new_tensor([settings.translation_lr] * 3 + [settings.rotation_lr] * 3)
            self.delta.sub_(rates * grad)
            self._clamp_to_bounds(settings)
        self.delta.grad = None

    def move_to(self, delta: torch.Tensor, settings: PosesConfig) -> None:
        """Set the correction to ``delta`` (a step found some other way), clamped to the bounds."""
        if self.held:
            return
        self.steps += 1
        with torch.no_grad():
            self.delta.copy_(delta)
            self._clamp_to_bounds(settings)
        self.delta.grad = None

    def _clamp_to_bounds(self, settings: PosesConfig) -> None:
        self._clamp(self.delta[:3], settings.max_translation)
        self._clamp(self.delta[3:], math.radians(settings.max_rotation))

    def _clamp(self, part: torch.Tensor, bound: float) -> None:
        """Scale ``part`` back to ``bound`` where it is longer, on the device (times exactly 1 where it is not)."""
        norm = part.norm()
        torch.maximum(self.hit_bound, (norm > bound).to(norm.dtype), out=self.hit_bound)
        part.mul_((bound / norm.clamp_min(torch.finfo(norm.dtype).tiny)).clamp(max=1.0))

    def report(self, c2w: torch.Tensor) -> PoseReport:
        """This correction of the client's ``c2w`` as results report it."""
        with torch.no_grad():  # one copy from the device: the correction, whether it was clamped, the pose
            values = torch.cat([self.delta.double(), self.hit_bound.double().reshape(1),
                                self.refined(c2w).double().reshape(-1)]).cpu().numpy()
        return PoseReport(values[:3], values[3:6], bool(values[6]), values[7:].reshape(4, 4))

    def state(self) -> torch.Tensor:
        """Everything it carries as one float64 row: delta, steps, clamped, held (for checkpoints)."""
        extra = torch.tensor([self.steps, float(self.clamped), float(self.held)], dtype=torch.float64)
        return torch.cat([self.delta.detach().double().cpu(), extra])

    @classmethod
    def from_state(cls, row: torch.Tensor, device: torch.device | str, dtype: torch.dtype) -> PoseCorrection:
        """The correction a ``state`` row holds; ValueError when it is not one."""
        if row.dim() != 1 or row.shape[0] not in STATE_SIZES or not bool(torch.isfinite(row).all()):
            raise ValueError(f"a pose correction is {STATE_SIZE} finite numbers, got shape {tuple(row.shape)}")
        correction = cls(device, dtype)
        with torch.no_grad():
            correction.delta.copy_(row[:6])
        correction.steps = int(row[6])
        correction.clamped = bool(row[7])
        correction.held = bool(row[8]) if row.shape[0] > 8 else False
        return correction

