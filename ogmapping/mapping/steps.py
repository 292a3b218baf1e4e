"""The mapping steps: each trains the map on a view and a freshly drawn window of keyframes, and every
``refine.interval`` steps of the session the anchors grow and are pruned.

A step decodes every view's anchors in view, rasterizes the window in one batch, weighs each view's
loss (``loss.view``; with ``keyframes.exposure`` on its render's colour corrected by the view's exposure),
backpropagates, gathers the screen-space gradients refinement grows from (with ``render.absgrad`` their
absolute sums), and steps Adam (the exposures of the views drawn with it; with ``optim.selective`` only the
anchor rows the views saw), the hash grid's lazy Adam, the map's moving average and the pose corrections
that move.
"""

from __future__ import annotations

import threading

import torch

from ogmapping.frames.geometry import world_to_camera
from ogmapping.mapping.model import MapModel
from ogmapping.model.gaussians import GaussianSet, generate_window
from ogmapping.model.static_gaussians import DrawnGaussianSet, DrawnWindow, frustum_camera
from ogmapping.optim import refine
from ogmapping.optim.exposure import values_of
from ogmapping.optim.keyframes import Keyframe, KeyframeSet, View
from ogmapping.optim.losses import same_size_groups
from ogmapping.optim.poses import PoseCorrection
from ogmapping.optim.window_poses import Basis, StepRates, step_corrections
from ogmapping.render import rasterize_batch
from ogmapping.render.output import RenderOutput
from ogmapping.runtime.time_budget import Budget, Stop


class MappingSteps:
    """Trains ``model`` on views and windows drawn from ``keyframes``; ``lock`` (the mapper's) is held
    per step, so queries are served between steps."""

    def __init__(self, model: MapModel, keyframes: KeyframeSet, lock: threading.RLock) -> None:
        self.model = model
        self.keyframes = keyframes
        self.lock = lock
        self._bases: dict[tuple[torch.device, torch.dtype], tuple[Basis, torch.Tensor]] = {}
        self._rates: tuple[tuple, StepRates] | None = None

    def run(self, iterations: int, view: View | None, view_is_newest: bool, budget: Budget,
            started: float) -> tuple[torch.Tensor, int, int, Stop | None]:
        """Up to ``iterations`` steps, each on ``view`` and a freshly drawn window of keyframes (the
        newest one is ``view`` itself when ``view_is_newest``); grow and prune every
        ``refine.interval`` steps of the whole session (frames may get fewer steps than that).
        Returns the last loss (a tensor on the device: NaN without steps), the anchors grown, the steps
        done and why they stopped short, if they did."""
        model = self.model
        loss, grown = torch.full((), float("nan")), 0
        for done in range(iterations):
            if (stopped := budget.stop(started)) is not None:
                return loss, grown, done, stopped
            with self.lock:
                loss = self.step(view, self.keyframes.draw_window(view_is_newest))
                model.iterations += 1
                if model.iterations % model.config.refine.interval == 0:
                    grown += self._refine()
        return loss, grown, iterations, None

    def _refine(self) -> int:
        """Grow anchors where the gradients ask for them, prune the faint ones; returns the anchors grown."""
        model, config = self.model, self.model.config
        with model.timed("refine"):
            refined = refine.refine(model.anchors, model.octree, config.refine, config.octree.voxel_size,
                                    model.optimizer)
            refine.end_interval(model.anchors)
        return refined.grown

    def step(self, view: View, keyframes: list[Keyframe]) -> torch.Tensor:
        """One optimisation step on ``view`` and ``keyframes``; returns its loss as a tensor on the
        device (reading it on the host would wait for the step to finish)."""
        model, config = self.model, self.model.config
        model.optimizer.zero_grad(set_to_none=True)
        if model.hash_optimizer is not None:
            model.hash_optimizer.zero_grad()
        total, renders, corrections = self.objective(view, keyframes)
        with model.timed("backward"):
            if total.requires_grad:
                total.backward()
        static = model.profile.static_shapes
        with model.timed("statistics"):
            accumulate = model.graphs.statistics if static else refine.accumulate
            for gaussians, output, drawn in renders:
                grad = output.screen_gradient(absolute=config.render.absgrad)
                accumulate(model.anchors, gaussians, grad, output.visible, drawn.intrinsics.width,
                           drawn.intrinsics.height)
        with model.timed("optimizer"):
            if config.optim.selective:
                model.optimizer.select(seen_rows(model.anchors.capacity, renders))
            model.optimizer.step()
            if model.hash_optimizer is not None:
                model.hash_optimizer.step()
            model.average.update(model.graphs.average)
            if corrections:
                step_corrections(corrections, self.step_rates(), model.graphs.pose_step)
        model.drawn.post(renders[0][0].drawn_count())
        return total.detach()

    def objective(self, view: View, keyframes: list[Keyframe]) -> tuple[
            torch.Tensor, list[tuple[GaussianSet, RenderOutput, View]], list[PoseCorrection]]:
        """A step's loss over ``view`` and ``keyframes``, its renders (Gaussians, output, view) and the
        pose corrections it moves."""
        model = self.model
        with model.timed("window"):
            window = [view, *(self.drawn(keyframe) for keyframe in keyframes)]
            poses, viewmats, corrections = self.poses(window, view)
        static = model.profile.static_shapes
        with model.timed("decode"):
            views = list(zip(poses, window, strict=True))
            decoded = self.decode_static(views) if static else self.decode(views)
            window_gaussians = decoded.views() if static else decoded
        with model.timed("rasterize"):
            cameras = [model.viewed(viewmat, drawn.intrinsics) for viewmat, drawn in zip(viewmats, window, strict=True)]
            outputs = rasterize_batch(decoded, cameras, backend=model.backend, options=model.raster_options)
        renders = list(zip(window_gaussians, outputs, window, strict=True))
        total = torch.zeros((), device=model.device)
        weights = self.window_weights(keyframes)
        weight_sum = sum(weights)
        with model.timed("loss"):
            for loss, weight in zip(self.view_losses(renders), weights, strict=True):
                total = total + loss * weight / weight_sum
        return total, renders, corrections

    def poses(self, window: list[View], view: View) -> tuple[list[torch.Tensor], list[torch.Tensor],
                                                             list[PoseCorrection]]:
        """Each of ``window``'s poses to render at (no gradient) and its world-to-camera, and the corrections the
        step moves (``moves``; their priors' gradients join their steps, ``window_poses.StepRates``). Where a view
        carries a correction the window is one batch, its world-to-cameras differentiable in those that move."""
        if all(drawn.correction is None for drawn in window):
            poses = [drawn.c2w for drawn in window]
            return poses, list(world_to_camera(torch.stack(poses)).unbind(0)), []
        moving = [self.moves(drawn.correction, view) for drawn in window]
        basis, still = self._basis(view.c2w)
        deltas = [still if drawn.correction is None else
                  drawn.correction.delta if moves else drawn.correction.delta.detach()
                  for drawn, moves in zip(window, moving, strict=True)]
        poses, viewmats = self.model.graphs.poses(deltas, [drawn.c2w for drawn in window], basis)
        corrections = {id(drawn.correction): drawn.correction for drawn, moves in zip(window, moving, strict=True)
                       if moves}
        viewmats = [viewmat if moves else viewmat.detach() for viewmat, moves in zip(viewmats, moving, strict=True)]
        return list(poses), viewmats, list(corrections.values())

    def _basis(self, like: torch.Tensor) -> tuple[Basis, torch.Tensor]:
        """The pose batch's constants and the correction of a view without one (zeros), on ``like``'s device and
        precision, made once."""
        key = (like.device, like.dtype)
        if key not in self._bases:
            self._bases[key] = (Basis.on(like.device, like.dtype), torch.zeros(6, device=like.device, dtype=like.dtype))
        return self._bases[key]

    def step_rates(self) -> StepRates:
        """The corrections' step on the device, made once per ``poses`` settings."""
        settings, model = self.model.config.poses, self.model
        key = (tuple(vars(settings).items()), model.device, model.profile.precision)
        if self._rates is None or self._rates[0] != key:
            self._rates = (key, StepRates.of(settings, model.device, model.profile.precision))
        return self._rates[1]

    def view_losses(self, renders: list[tuple[GaussianSet, RenderOutput, View]]) -> list[torch.Tensor]:
        """Each render's ``mapping_loss``: per view, or with the Triton loss (``profile.triton_loss``) per
        group of views of one image size, in one batch."""
        model, config = self.model, self.model.config
        static = model.profile.static_shapes
        if not model.profile.triton_loss:
            return [model.graphs.view_loss(output.color, output.depth, drawn.rgb, drawn.depth, gaussians.scales,
                                           config.loss, drawn.ssim_reference, compiled=model.profile.compiled,
                                           drawn=gaussians.drawn if static else None,
                                           exposure=self.exposure(drawn))[0]
                    for gaussians, output, drawn in renders]
        losses: dict[int, torch.Tensor] = {}
        for group in same_size_groups([output.color for _, output, _ in renders]):
            chosen = [renders[position] for position in group]
            batch = model.graphs.window_loss(
                [output.color for _, output, _ in chosen], [output.depth for _, output, _ in chosen],
                [drawn.rgb for _, _, drawn in chosen], [drawn.depth for _, _, drawn in chosen],
                [gaussians.scales for gaussians, _, _ in chosen], config.loss,
                [drawn.ssim_reference for _, _, drawn in chosen],
                [gaussians.drawn if static else None for gaussians, _, _ in chosen],
                torch.stack([self.exposure(drawn) for _, _, drawn in chosen]) if config.keyframes.exposure else None)
            losses.update(zip(group, batch.unbind(), strict=True))
        return [losses[position] for position in range(len(renders))]

    def exposure(self, view: View) -> torch.Tensor | None:
        """The (a, b) ``view``'s render is corrected by in its loss: none without ``keyframes.exposure``,
        else its own or, for the first keyframe, the identity (one tensor per view either way, so the
        loss's graphs keep their inputs' shapes)."""
        return values_of(view.exposure, self.model.device) if self.model.config.keyframes.exposure else None

    def decode_static(self, views: list[tuple[torch.Tensor, View]]) -> DrawnWindow:
        """The Gaussians of every buffer row seen from each (pose, view), stacked, the ones not drawn inert: from
        the Triton kernels where the profile says so (``profile.triton_decode``)."""
        model = self.model
        poses = torch.stack([pose.detach() for pose, _ in views])
        cameras = torch.stack([frustum_camera(drawn.intrinsics, model.device) for _, drawn in views])
        return model.graphs.decode(model.anchors, model.buffer_features(), model.decoders, poses, cameras, model.far,
                                   fused=model.profile.triton_decode)

    def decode(self, views: list[tuple[torch.Tensor, View]]) -> list[GaussianSet]:
        """The Gaussians of the anchors in view of each (pose, view)."""
        model = self.model
        rows = [model.rows_in_view(pose.detach(), drawn.intrinsics) for pose, drawn in views]
        centers = [pose.detach()[:3, 3] for pose, _ in views]
        return generate_window(model.anchors, model.window_features(rows), model.decoders, centers, rows,
                               compiled=model.profile.compiled, shared_decode=model.profile.shared_decode)

    def moves(self, correction: PoseCorrection | None, view: View) -> bool:
        """Whether a step moves ``correction``: not one held at the client's pose by its tracking, and not
        the view's without ``poses.view_steps`` (the view then keeps the pose its tracking found)."""
        if correction is None or correction.held:
            return False
        return self.model.config.poses.view_steps or correction is not view.correction

    def window_weights(self, keyframes: list[Keyframe]) -> list[float]:
        """Loss weights of a step's view and its window ``keyframes``: ``loss.view`` for the view once
        the window is full, else 1, and 1 for each keyframe. Keyframes hold what the map has to keep;
        a streamed view, what the camera sees now (bench/RESULTS.md "Loss weights")."""
        view = self.model.config.loss.view if self.keyframes.is_full() else 1.0
        return [view] + [1.0] * len(keyframes)

    def drawn(self, keyframe: Keyframe) -> View:
        """A drawn keyframe as a view on the device: full size if it is local, else downscaled."""
        if not self.keyframes.is_local(keyframe):
            keyframe = keyframe.downscaled(self.window_scale(keyframe.intrinsics.width))
        model = self.model
        images = model.graphs.keyframe_images if model.profile.static_shapes else None
        return keyframe.view(model.device, compiled=model.profile.compiled, images=images)

    def window_scale(self, width: int) -> float:
        """Scale for a global window keyframe: ``window_scale``, but not below ``window_min_width``
        pixels. The view and local keyframes stay full size: they supervise what the view sees
        (half-size local keyframes cost 1.6 dB on Replica room0 at 600x340, bench/RESULTS.md)."""
        settings = self.model.config.keyframes
        return min(1.0, max(settings.window_scale, settings.window_min_width / width))


def seen_rows(capacity: int, renders: list[tuple[GaussianSet, RenderOutput, View]]) -> torch.Tensor:
    """(capacity,) bool: the anchor rows with a Gaussian drawn and visible in one of ``renders``, the rows
    ``optim.selective`` steps (counted by a scatter, not gathered: nothing for the host to wait on)."""
    device = renders[0][1].visible.device
    hits = torch.zeros(capacity, dtype=torch.int32, device=device)
    for gaussians, output, _ in renders:
        counted = output.visible & gaussians.drawn if isinstance(gaussians, DrawnGaussianSet) else output.visible
        hits.index_add_(0, gaussians.rows, counted.to(torch.int32))
    return hits > 0
