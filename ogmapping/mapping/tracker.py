"""Pose tracking: a frame's pose corrected against the map as it stands, before the frame adds to it.

Three stages on a pose the map holds fixed (its Gaussians decoded once, from the client's pose):
gradient steps on every ``poses.track_stride``-th pixel, whose first few tell a pose that moves from
one that has settled (``poses.settled``); on a pose that moves, Gauss-Newton steps
(``ogmapping.optim.pose_newton``), then gradient steps on every pixel.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import torch

from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.frame import Frame
from ogmapping.mapping.model import MapModel
from ogmapping.model.gaussians import GaussianSet
from ogmapping.optim.losses import TrackingMask, tracking_loss, tracking_mask, tracking_residuals
from ogmapping.optim.pose_newton import Residuals, newton_track
from ogmapping.optim.poses import TRACK_CHECK_STEPS, PoseCorrection, settled
from ogmapping.render import rasterize
from ogmapping.render.output import RenderOutput
from ogmapping.render.rules import COVARIANCE_BLUR
from ogmapping.runtime.time_budget import Budget

# A render of a frame's tracked pixels at a correction of its pose, and those pixels' colour and depth.
TrackingRenderer = tuple[Callable[[PoseCorrection], RenderOutput], torch.Tensor, torch.Tensor]
# A prepared frame's colour, depth and pose on the mapper's device.
FrameTensors = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


class Tracker:
    """Tracks frames against ``model``; ``lock`` is the mapper's, held while the map is read."""

    def __init__(self, model: MapModel, lock: threading.RLock) -> None:
        self.model = model
        self.lock = lock

    def track(self, intrinsics: Intrinsics, tensors: FrameTensors, correction: PoseCorrection, budget: Budget,
              started: float, rows_below: int | None = None) -> None:
        """``poses.track_iterations`` steps on the pose of a prepared frame (its colour camera's ``intrinsics``,
        its colour, depth and pose as device ``tensors``) alone, on every
        ``poses.track_stride``-th pixel, the map held fixed, until ``budget`` says stop. With
        ``poses.track_min_gain`` a pose that ``settled`` after TRACK_CHECK_STEPS steps goes back to the
        client's and is held there, its tracking cut short; one that moves then takes
        ``poses.track_newton_iterations`` Gauss-Newton steps and ``poses.track_fine_iterations`` gradient
        steps on every pixel. ``rows_below``: the map is its anchors in rows below it (those the frame found,
        where it has added its own since)."""
        settings = self.model.config.poses
        if not settings.track_iterations:
            return
        with self.lock, self.model.timed("track"):
            gaussians = self._gaussians(intrinsics, tensors[2], rows_below)
            renderer = self._renderer(intrinsics, tensors, None, gaussians)
            loss_at = self._loss_of(renderer)
            losses: list[torch.Tensor] = []  # before each step, then after the check's steps
            for _ in range(settings.track_iterations):
                if budget.stop(started) is not None:
                    return
                loss = loss_at(correction)
                losses.append(loss.detach())
                if len(losses) == TRACK_CHECK_STEPS + 1 and settled(losses, settings.track_min_gain):
                    correction.hold()
                    return
                (loss + correction.prior(settings)).backward()
                correction.step(settings)
            if len(losses) == TRACK_CHECK_STEPS and settings.track_min_gain:  # the check's third loss
                with torch.no_grad():
                    losses.append(loss_at(correction))
                if settled(losses, settings.track_min_gain):
                    correction.hold()
            if correction.held:
                return
            if settings.track_newton_iterations:
                newton_track(self._residuals_of(renderer), correction, settings,
                             settings.track_newton_iterations, lambda: budget.stop(started) is not None)
            if not settings.track_fine_iterations:
                return
            fine = self._loss_of(self._renderer(intrinsics, tensors, 1, gaussians))
            for _ in range(settings.track_fine_iterations):
                if budget.stop(started) is not None:
                    return
                (fine(correction) + correction.prior(settings)).backward()
                correction.step(settings)

    def review(self, intrinsics: Intrinsics, tensors: FrameTensors, correction: PoseCorrection,
               stop: Callable[[], bool] = lambda: False) -> None:
        """Put a keyframe's ``correction`` back at the client's pose where that pose fits the keyframe (its colour
        camera's ``intrinsics``, its colour, depth and client pose as device ``tensors``) better: its tracking
        loss against the map as it stands is lower there. Mapping steps move a correction by the gradient
        alone, so one that fit the young map's error early can stay caught a few pixels off, where the map has
        since settled around the client's pose (bench/RESULTS.md, "Corrections reviewed"). Decided on the device:
        no read (the decode's frustum test waits, as tracking's does). Then ``poses.review_newton_iterations``
        Gauss-Newton steps on every ``poses.review_newton_stride``-th pixel of the same decode, until ``stop()``:
        the keyframe re-tracked against the map."""
        settings = self.model.config.poses
        with self.lock, self.model.timed("track"), torch.no_grad():
            gaussians = self._gaussians(intrinsics, tensors[2])
            loss_at = self._loss_of(self._renderer(intrinsics, tensors, None, gaussians))
            keep = loss_at(correction) < loss_at(PoseCorrection(self.model.device, correction.delta.dtype))
            correction.delta.mul_(keep.to(correction.delta.dtype))
            if settings.review_newton_iterations:
                renderer = self._renderer(intrinsics, tensors, settings.review_newton_stride, gaussians)
                newton_track(self._residuals_of(renderer), correction, settings, settings.review_newton_iterations,
                             stop)

    def _gaussians(self, intrinsics: Intrinsics, c2w: torch.Tensor, rows_below: int | None = None) -> GaussianSet:
        """The Gaussians of the anchors (in rows below ``rows_below``, if given) a frame sees from its client's pose
        ``c2w``, decoded from there: the fixed map its tracking steps render, on any of its pixels (a stride keeps
        the frustum)."""
        with self.lock, torch.no_grad():
            rows = self.model.rows_in_view(c2w, intrinsics)
            if rows_below is not None:
                rows = rows[rows < rows_below]
            return self.model.decode(c2w[:3, 3], rows)

    def objective(self, frame: Frame, stride: int | None = None,
                  gaussians: GaussianSet | None = None) -> Callable[[PoseCorrection], torch.Tensor]:
        """The tracking loss of ``frame`` (prepared) as a function of its pose's correction: its every
        ``stride``-th pixel (None: ``poses.track_stride``) against the map as it stands, its ``gaussians``
        (``gaussians``, decoded here when not given), rendered at those pixels' own centres with the
        full-size blur, so the loss is the full-size loss on those pixels. Call the function it returns
        with the mapper's lock held, before the map changes."""
        return self._loss_of(self._renderer(frame.color_intrinsics, self.model.tensors(frame), stride, gaussians))

    def residuals(self, frame: Frame, stride: int | None = None, gaussians: GaussianSet | None = None) -> Residuals:
        """``objective`` as per-pixel residuals of a correction's ``delta`` (no gradient), over a given mask
        or, given None, the pixels this render covers: what Gauss-Newton tracking steps on."""
        return self._residuals_of(self._renderer(frame.color_intrinsics, self.model.tensors(frame), stride, gaussians))

    def _loss_of(self, renderer: TrackingRenderer) -> Callable[[PoseCorrection], torch.Tensor]:
        render_at, rgb, depth = renderer
        config = self.model.config

        def loss_at(correction: PoseCorrection) -> torch.Tensor:
            output = render_at(correction)
            return tracking_loss(output.color, output.depth, output.alpha, rgb, depth, config.loss,
                                 config.poses.track_alpha)

        return loss_at

    def _residuals_of(self, renderer: TrackingRenderer) -> Residuals:
        render_at, rgb, depth = renderer
        config = self.model.config
        probe = PoseCorrection(self.model.device)

        def residuals_at(delta: torch.Tensor, mask: TrackingMask | None) -> tuple[torch.Tensor, TrackingMask]:
            with torch.no_grad():
                probe.delta.copy_(delta)
                output = render_at(probe)
                if mask is None:
                    mask = tracking_mask(output.alpha, depth, config.poses.track_alpha)
                return tracking_residuals(output.color, output.depth, rgb, depth, config.loss, mask), mask

        return residuals_at

    def _renderer(self, intrinsics: Intrinsics, tensors: FrameTensors, stride: int | None,
                  gaussians: GaussianSet | None) -> TrackingRenderer:
        """A render of a frame's every ``stride``-th pixel at a correction of its pose (see ``objective``), and
        those pixels' colour and depth (from row and column 0: the same pixels at the same centres)."""
        rgb, depth, c2w = tensors
        if gaussians is None:
            gaussians = self._gaussians(intrinsics, c2w)
        stride = self.model.config.poses.track_stride if stride is None else stride
        rgb, depth = rgb[::stride, ::stride].contiguous(), depth[::stride, ::stride].contiguous()
        intrinsics = intrinsics.strided(stride, 0)
        blur = COVARIANCE_BLUR / stride**2

        def render_at(correction: PoseCorrection) -> RenderOutput:
            camera = self.model.camera(correction.refined(c2w), intrinsics, blur)
            return rasterize(gaussians, camera, backend=self.model.backend, options=self.model.raster_options)

        return render_at, rgb, depth
