"""The online mapper: frames in, an optimised anchor map out (its place in the data flow: docs/architecture.md).

process(frame): register depth, allocate coarse anchors for newly observed space, decide whether
the frame is a keyframe, and if so optimise k iterations, each on a freshly drawn keyframe
window, growing and pruning anchors every m iterations.

All public methods are thread-safe: ``lock`` is held per optimisation iteration, so a render or a
stats request from another thread is served between iterations. Device, backend, torch threads and
whether the compiled CPU kernels run are fixed once, in ``profile`` (``ogmapping.runtime.profile``).
On CUDA each mapper runs its device work on a stream of its own (``ogmapping.runtime.streams``), so
mappers driven from separate threads overlap on the device: every public method that touches the
device runs on it, and device tensors cross it only through ``handed_in`` and ``handed_out``.
"""

from __future__ import annotations

import copy
import threading
import time
from collections.abc import Callable
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, fields

import numpy as np
import torch

from ogmapping.config import ConfigBounds, MapperConfig, by_resolution
from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.frame import Frame
from ogmapping.frames.geometry import intrinsics_matrix, world_to_camera
from ogmapping.frames.preprocess import prepare, stride_frame
from ogmapping.model.decoders import Decoders
from ogmapping.model.encoding import HashGridEncoding, feature_dim, initial_anchor_features
from ogmapping.model.gaussians import GaussianSet, anchors_in_view, decoded_logits, generate, generate_window
from ogmapping.optim import refine
from ogmapping.optim.averaging import MapAverage
from ogmapping.optim.keyframes import Keyframe, KeyframeSet, View
from ogmapping.optim.lazy_adam import LazyAdam
from ogmapping.optim.losses import TrackingMask, mapping_loss, tracking_loss, tracking_mask, tracking_residuals
from ogmapping.optim.pose_newton import Residuals, newton_track
from ogmapping.optim.poses import TRACK_CHECK_STEPS, PoseCorrection, PoseReport, settled
from ogmapping.optim.step_budget import step_count_multiple, step_multiple
from ogmapping.persist import snapshot, training
from ogmapping.persist.state import MapState
from ogmapping.render import Camera, rasterize, rasterize_batch
from ogmapping.render.output import RenderOutput
from ogmapping.render.rules import COVARIANCE_BLUR
from ogmapping.runtime.profile import execution_profile
from ogmapping.runtime.stage_timer import StageTimer
from ogmapping.runtime.streams import handed_in, handed_out, on_stream, session_stream
from ogmapping.runtime.threads import torch_threads
from ogmapping.runtime.time_budget import Budget, Stop
from ogmapping.stats import MapStats, PoseSummary
from ogmapping.structure import allocation
from ogmapping.structure.anchor_colour import cell_colour_logits, colour_sample_stride
from ogmapping.structure.anchors import AnchorMap
from ogmapping.structure.octree import SparseVoxelOctree

# A render of a frame's tracked pixels at a correction of its pose, and those pixels' colour and depth.
TrackingRenderer = tuple[Callable[[PoseCorrection], RenderOutput], torch.Tensor, torch.Tensor]


@dataclass
class FrameResult:
    index: int
    keyframe: bool
    anchors: int
    gaussians: int
    iterations: int
    new_anchors: int
    loss: float
    seconds: float
    stopped: Stop | None = None  # why optimisation ended before ``iterations`` reached the planned count
    pose: PoseReport | None = None  # the frame's pose after its steps (``poses.refine``; else the client's)


@dataclass(frozen=True)
class KeyframePose:
    """A keyframe's pose as the client gave it and as refinement left it (the same without refinement)."""

    index: int
    client_c2w: np.ndarray  # (4, 4)
    refined_c2w: np.ndarray  # (4, 4)
    clamped: bool


@dataclass
class Rendered:
    color: np.ndarray  # (H, W, 3) float32 in [0, 1]
    depth: np.ndarray  # (H, W) float32 metres, 0 where nothing was rendered
    alpha: np.ndarray  # (H, W) float32


class Mapper:
    """One session's map and the optimisation that builds it."""

    def __init__(self, config: MapperConfig, device: str | torch.device = "cpu") -> None:
        # A copy: the first frame may resolve values that depend on its resolution (``_fit_to``).
        self.config = copy.deepcopy(config)
        self.profile = execution_profile(device, config.backend, config.model.encoding)
        self.stream = session_stream(self.device)
        self.lock = threading.RLock()
        # Each session draws from its own generator: sessions mapping side by side in one server
        # would otherwise interleave draws from torch's global one (and reseed it for each other).
        self.generator = torch.Generator().manual_seed(config.seed)
        with on_stream(self.stream):
            self._build_model(self.config)
        self.keyframes = KeyframeSet(self.config.keyframes, config.seed, self._footprint)
        self.frames = 0
        self.iterations = 0
        # Sum of the mapped frames' camera centres (float64): their mean is where a .ply export
        # bakes view-dependent colour by default, and it survives snapshots.
        self.camera_position_sum = torch.zeros(3, dtype=torch.float64)
        self.camera_positions = 0
        self.last_gaussians = 0
        self.timer = StageTimer.for_device(self.device)

    def _build_model(self, config: MapperConfig) -> None:
        """The map's structures, decoders and optimisers, made on the device (on the mapper's stream)."""
        model = config.model
        self.octree = SparseVoxelOctree.from_config(config.octree, self.device)
        self.anchors = AnchorMap(model.n_offsets, model.feature_dim, model.encoding == "anchor", self.device,
                                 with_colours=model.anchor_colour)
        self.encoding = HashGridEncoding(model, self.generator).to(self.device) if model.encoding == "hash" else None
        self.decoders = Decoders(feature_dim(model), model.n_offsets, model.hidden_dim, self.generator)
        self.decoders = self.decoders.to(self.device)
        self.optimizer = self._make_optimizer()
        self.average = MapAverage(self.anchors, self.decoders, config.optim.average_decay, config.optim.average_growth)
        self.hash_optimizer = (LazyAdam(self.encoding.table, self.encoding.gradients, config.optim.hash_lr,
                                        compiled=self.profile.compiled)
                               if self.encoding is not None else None)

    @property
    def device(self) -> torch.device:
        return self.profile.device

    @property
    def backend(self) -> str:
        return self.profile.backend

    @property
    def timings(self) -> dict[str, float]:
        """Seconds per stage so far (``StageTimer``; on CUDA, reading them waits for the device)."""
        return self.timer.totals()

    def _make_optimizer(self) -> torch.optim.Adam:
        lr = self.config.optim
        groups = [
            {"params": [self.anchors.log_scales], "lr": lr.scaling_lr, "name": "log_scales"},
            {"params": [self.anchors.offsets], "lr": lr.offsets_lr, "name": "offsets"},
            {"params": self.decoders.opacity.parameters(), "lr": lr.opacity_mlp_lr, "name": "opacity_mlp"},
            {"params": self.decoders.color.parameters(), "lr": lr.color_mlp_lr, "name": "color_mlp"},
            {"params": self.decoders.cov.parameters(), "lr": lr.cov_mlp_lr, "name": "cov_mlp"},
        ]
        if self.encoding is None:
            groups.append({"params": [self.anchors.features], "lr": lr.features_lr, "name": "features"})
        if self.anchors.with_colours:
            groups.append({"params": [self.anchors.colours], "lr": lr.colour_lr, "name": "colours"})
        return torch.optim.Adam(groups, eps=1e-15)

    def _timed(self, stage: str) -> AbstractContextManager[None]:
        """Add the block's time to stage ``stage`` of ``timings``: the host's on the CPU; on CUDA the
        device's between the stage's start and end on the mapper's stream, measured with events the
        host never waits for while mapping (``ogmapping.runtime.stage_timer``)."""
        return self.timer.stage(stage)

    # ------------------------------------------------------------------ mapping

    def process(self, frame: Frame, budget: Budget | None = None) -> FrameResult:
        """Map one frame; returns what happened to it. Optimisation ends early once ``budget`` says stop."""
        with on_stream(self.stream), torch_threads(self.profile.threads):
            return self._process(frame, budget or Budget())

    def _process(self, frame: Frame, budget: Budget) -> FrameResult:
        start = time.perf_counter()
        with self._timed("preprocess"):
            frame = prepare(frame, self.config.octree.depth_min, self.config.octree.depth_max)
            self._fit_to(frame.color_intrinsics)
            rgb, depth, c2w = self._tensors(frame)
        # With ``poses.refine`` every frame but the first keyframe's carries a correction of its client pose
        # (the first keeps it: the map stays in the client's frame), tracked against the map before this
        # frame adds to it; the frame is placed at the tracked pose, and its steps refine it further.
        correction = PoseCorrection(self.device, c2w.dtype) if self.config.poses.refine and self.keyframes else None
        placed = c2w
        if correction is not None:
            self._track(frame, correction, budget, start)
            placed = correction.refined(c2w).detach()
        with self.lock, self._timed("allocate"):
            sampled = allocation.sampled_depth(self.config.octree, depth, frame.color_intrinsics)
            new_codes = allocation.allocate(self.config.octree.allocation, self.octree, sampled,
                                            frame.color_intrinsics, placed,
                                            lambda: self._render(placed, frame.color_intrinsics)[1])
            self._add_coarse_anchors(new_codes, rgb, depth, frame.color_intrinsics, placed)
        with self._timed("keyframes"):
            codes = self.octree.seen_from(depth, frame.color_intrinsics, placed)
            is_keyframe = self.keyframes.should_insert(codes)
            multiple = step_count_multiple(self.config.keyframes, frame.color_intrinsics)
            iterations = multiple * self._iterations_for(is_keyframe)
            if is_keyframe:
                self.keyframes.insert(Keyframe.capture(frame.index, rgb, depth, frame.color_intrinsics, c2w, codes,
                                                       pinned=self.device.type == "cuda", correction=correction))
        # The frame itself, at full precision, is the view every step trains on.
        view = (View.of(rgb, depth, frame.color_intrinsics, c2w, compiled=self.profile.compiled, correction=correction)
                if iterations else None)
        loss, grown, done, stopped = self._optimise(iterations, view, is_keyframe, budget, start)
        with self.lock:
            pose = correction.report(c2w) if correction is not None else PoseReport.unrefined(frame.c2w)
        self.frames += 1
        self.camera_position_sum += torch.as_tensor(frame.c2w[:3, 3], dtype=torch.float64)
        self.camera_positions += 1
        return FrameResult(
            index=frame.index,
            keyframe=is_keyframe,
            anchors=len(self.anchors),
            gaussians=self.last_gaussians,
            iterations=done,
            new_anchors=int(new_codes.numel()) + grown,
            loss=loss,
            seconds=time.perf_counter() - start,
            stopped=stopped,
            pose=pose,
        )

    def _tensors(self, frame: Frame) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """A prepared frame's colour, depth and pose on the device, at the mapper's precision."""
        return tuple(torch.as_tensor(array, dtype=self.profile.precision, device=self.device)
                     for array in (frame.rgb, frame.depth, frame.c2w))

    def _fit_to(self, intrinsics: Intrinsics) -> None:
        """On the first frame, the config's by-resolution switches resolved against the frame's step multiple
        (``ogmapping.config.by_resolution``); a model whose shape changes is rebuilt (still empty), drawn
        afresh from the seed. A multiple of 1 keeps everything as it was, so such maps are exactly as
        without the switches."""
        if self.frames or len(self.anchors) or not by_resolution.pending(self.config):
            return
        resolved = by_resolution.resolve_switches(self.config, step_multiple(self.config.keyframes, intrinsics))
        optim = self.config.optim
        if resolved.averaged:
            self.average = MapAverage(self.anchors, self.decoders, optim.average_decay, optim.average_growth)
        if resolved.reshaped:
            self.generator.manual_seed(self.config.seed)
            with self.lock:
                self._build_model(self.config)

    def _add_coarse_anchors(self, codes: torch.Tensor, rgb: torch.Tensor, depth: torch.Tensor,
                            intrinsics: Intrinsics, c2w: torch.Tensor) -> None:
        """New coarsest-level anchors for ``codes``, observed in the frame of ``rgb`` and ``depth``
        (with ``anchor_colour_start`` "cell", each starts with the mean colour of the frame's points
        in its cell)."""
        count = int(codes.numel())
        if count == 0:
            return
        levels = torch.zeros(count, dtype=torch.int64, device=self.device)
        sizes = torch.full((count,), self.octree.cell_size(0), device=self.device)
        positions = self.octree.centers(codes, 0)
        features = (
            initial_anchor_features(count, self.config.model.feature_dim, self.device, self.generator)
            if self.anchors.with_features else None
        )
        if self.iterations == 0 and not len(self.anchors) and self.config.model.initial_visible > 0:
            opacity, _, _ = self._decoded_logits(positions, features, c2w)
            self.decoders.start_visible(opacity, self.config.model.initial_visible)
        colours = None
        if self.anchors.with_colours and self.config.model.anchor_colour_start == "cell":
            stride = colour_sample_stride(self.config.octree.voxel_size, self.config.octree.depth_max, intrinsics)
            target, seen = cell_colour_logits(self.octree, codes, rgb, depth, intrinsics, c2w, stride)
            _, decoded, _ = self._decoded_logits(positions, features, c2w)
            colours = torch.where(seen.unsqueeze(1), target - decoded.view(count, -1, 3).mean(1), 0.0)
        self.anchors.add(codes, levels, positions, sizes, features, self.optimizer, colours)

    def _decoded_logits(self, positions: torch.Tensor, features: torch.Tensor | None,
                        c2w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The decoders' logits for new anchors at ``positions`` seen from ``c2w``, from their
        ``features`` (the sparse version's) or the hash grid's."""
        with torch.no_grad():
            if features is None:
                features = self.encoding(positions, compiled=self.profile.compiled)
            return decoded_logits(self.decoders, features, positions, c2w[:3, 3])

    def _footprint(self, keyframe: Keyframe) -> torch.Tensor:
        depth = keyframe.depth.to(self.device, non_blocking=keyframe.pinned).to(torch.float32)
        return self.octree.seen_from(depth, keyframe.intrinsics, keyframe.c2w)

    def _iterations_for(self, is_keyframe: bool) -> int:
        """k for a keyframe (more for the very first), ``frame_iterations`` for any other frame, but
        no more than ``frame_renders`` renders of the view and its window (at least one step); the
        frame then gets ``step_count_multiple`` times this (by the image's resolution).

        The cap bounds a streamed frame's cost as the window fills: with ``frame_renders`` 4 a frame
        with a full window (the view, a local and two global keyframes) takes one step, a frame whose
        only window keyframe is the newest takes two (bench/RESULTS.md; commit b0334d6, 2026-11-24)."""
        settings = self.config.keyframes
        if is_keyframe:
            return settings.first_iterations if not self.keyframes else settings.iterations
        if not self.keyframes or settings.frame_iterations == 0:
            return 0
        if settings.frame_renders == 0:
            return settings.frame_iterations
        renders_per_step = 1 + self.keyframes.window_size(view_is_newest=False)
        return min(settings.frame_iterations, max(1, settings.frame_renders // renders_per_step))

    def _track(self, frame: Frame, correction: PoseCorrection, budget: Budget, started: float) -> None:
        """``poses.track_iterations`` steps on the pose of ``frame`` (prepared) alone, on every
        ``poses.track_stride``-th pixel, the map held fixed (its Gaussians decoded once, from the client's pose),
        until ``budget`` says stop. With ``poses.track_min_gain`` a pose that ``settled`` after
        TRACK_CHECK_STEPS steps goes back to the client's and is held there, its tracking cut short; one
        that moves then takes ``poses.track_newton_iterations`` Gauss-Newton steps and
        ``poses.track_fine_iterations`` gradient steps on every pixel."""
        settings = self.config.poses
        if not settings.track_iterations:
            return
        with self.lock, self._timed("track"):
            gaussians = self._tracking_gaussians(frame)
            renderer = self._tracking_renderer(frame, None, gaussians)
            loss_at = self._tracking_loss_of(renderer)
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
                newton_track(self._tracking_residuals_of(renderer), correction, settings,
                             settings.track_newton_iterations, lambda: budget.stop(started) is not None)
            if not settings.track_fine_iterations:
                return
            fine = self.tracking_objective(frame, 1, gaussians)
            for _ in range(settings.track_fine_iterations):
                if budget.stop(started) is not None:
                    return
                (fine(correction) + correction.prior(settings)).backward()
                correction.step(settings)

    def _tracking_gaussians(self, frame: Frame) -> GaussianSet:
        """The Gaussians of the anchors ``frame`` (prepared) sees from its client's pose, decoded from there:
        the fixed map its tracking steps render, on any of its pixels (a stride keeps the frustum)."""
        _, _, c2w = self._tensors(frame)
        with self.lock, torch.no_grad():
            rows = self._rows_in_view(c2w, frame.color_intrinsics)
            return generate(self.anchors, self._features, self.decoders, c2w[:3, 3], rows,
                            compiled=self.profile.compiled)

    def tracking_objective(self, frame: Frame, stride: int | None = None,
                           gaussians: GaussianSet | None = None) -> Callable[[PoseCorrection], torch.Tensor]:
        """The tracking loss of ``frame`` (prepared) as a function of its pose's correction: its every
        ``stride``-th pixel (None: ``poses.track_stride``) against the map as it stands, its ``gaussians``
        (``_tracking_gaussians``, decoded here when not given), rendered at those pixels' own centres
        with the full-size blur, so the loss is the full-size loss on those pixels. Call the function it
        returns with the mapper's lock held, before the map changes."""
        return self._tracking_loss_of(self._tracking_renderer(frame, stride, gaussians))

    def tracking_residuals(self, frame: Frame, stride: int | None = None,
                           gaussians: GaussianSet | None = None) -> Residuals:
        """``tracking_objective`` as per-pixel residuals of a correction's ``delta`` (no gradient), over a
        given mask or, given None, the pixels this render covers: what Gauss-Newton tracking steps on."""
        return self._tracking_residuals_of(self._tracking_renderer(frame, stride, gaussians))

    def _tracking_loss_of(self, renderer: TrackingRenderer) -> Callable[[PoseCorrection], torch.Tensor]:
        render_at, rgb, depth = renderer
        settings = self.config.poses

        def loss_at(correction: PoseCorrection) -> torch.Tensor:
            output = render_at(correction)
            return tracking_loss(output.color, output.depth, output.alpha, rgb, depth, self.config.loss,
                                 settings.track_alpha)

        return loss_at

    def _tracking_residuals_of(self, renderer: TrackingRenderer) -> Residuals:
        render_at, rgb, depth = renderer
        probe = PoseCorrection(self.device)

        def residuals_at(delta: torch.Tensor, mask: TrackingMask | None) -> tuple[torch.Tensor, TrackingMask]:
            with torch.no_grad():
                probe.delta.copy_(delta)
                output = render_at(probe)
                if mask is None:
                    mask = tracking_mask(output.alpha, depth, self.config.poses.track_alpha)
                return tracking_residuals(output.color, output.depth, rgb, depth, self.config.loss, mask), mask

        return residuals_at

    def _tracking_renderer(self, frame: Frame, stride: int | None, gaussians: GaussianSet | None) -> TrackingRenderer:
        """A render of ``frame``'s every ``stride``-th pixel at a correction of its pose (see
        ``tracking_objective``), and those pixels' colour and depth."""
        if gaussians is None:
            gaussians = self._tracking_gaussians(frame)
        stride = self.config.poses.track_stride if stride is None else stride
        frame = stride_frame(frame, stride, 0)
        rgb, depth, c2w = self._tensors(frame)
        blur = COVARIANCE_BLUR / stride**2

        def render_at(correction: PoseCorrection) -> RenderOutput:
            camera = self._camera(correction.refined(c2w), frame.color_intrinsics)
            return rasterize(gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities,
                             gaussians.colors, camera.viewmat, camera.K, camera.width, camera.height,
                             backend=self.backend, blur=blur)

        return render_at, rgb, depth

    def _optimise(
        self, iterations: int, view: View | None, view_is_newest: bool, budget: Budget, started: float
    ) -> tuple[float, int, int, Stop | None]:
        """Up to ``iterations`` steps, each on ``view`` and a freshly drawn window of keyframes (the
        newest one is ``view`` itself when ``view_is_newest``); grow and prune every
        ``refine.interval`` steps of the whole session (frames may get fewer steps than that).
        Returns the last loss (read from the device once, after the loop), the anchors grown, the
        steps done and why they stopped short, if they did."""
        loss, grown = torch.full((), float("nan")), 0
        interval = self.config.refine.interval
        for done in range(iterations):
            if (stopped := budget.stop(started)) is not None:
                return float(loss), grown, done, stopped
            with self.lock:
                loss = self._iteration(view, self.keyframes.draw_window(view_is_newest))
                self.iterations += 1
                if self.iterations % interval == 0:
                    with self._timed("refine"):
                        grown += refine.grow(self.anchors, self.octree, self.config.refine,
                                             self.config.octree.voxel_size, self.optimizer)
                        refine.prune(self.anchors, self.config.refine, self.optimizer)
                        refine.end_interval(self.anchors)
        return float(loss), grown, iterations, None

    def _iteration(self, view: View, keyframes: list[Keyframe]) -> torch.Tensor:
        """One optimisation step on ``view`` and ``keyframes``; returns its loss as a tensor on the
        device (reading it on the host would wait for the step to finish)."""
        self.optimizer.zero_grad(set_to_none=True)
        if self.hash_optimizer is not None:
            self.hash_optimizer.zero_grad()
        with self._timed("window"):
            window = [view, *(self._drawn(keyframe) for keyframe in keyframes)]
            moving = [(drawn, self._moves(drawn.correction, view)) for drawn in window]
            poses = [drawn.pose() if moves else drawn.pose().detach() for drawn, moves in moving]
            corrections = list({id(drawn.correction): drawn.correction for drawn, moves in moving if moves}.values())
        with self._timed("decode"):
            views = list(zip(poses, window, strict=True))
            rows = [self._rows_in_view(pose.detach(), drawn.intrinsics) for pose, drawn in views]
            window_gaussians = generate_window(self.anchors, self._window_features(rows), self.decoders,
                                               [pose.detach()[:3, 3] for pose in poses], rows,
                                               compiled=self.profile.compiled, shared_decode=self.profile.shared_decode)
        with self._timed("rasterize"):
            cameras = [self._camera(pose, drawn.intrinsics) for pose, drawn in views]
            outputs = rasterize_batch(window_gaussians, cameras, backend=self.backend)
        renders = list(zip(window_gaussians, outputs, window, strict=True))
        total = torch.zeros((), device=self.device)
        weights = self._window_weights(keyframes)
        weight_sum = sum(weights)
        with self._timed("loss"):
            for (gaussians, output, drawn), weight in zip(renders, weights, strict=True):
                loss, _ = mapping_loss(output.color, output.depth, drawn.rgb, drawn.depth,
                                       gaussians.scales, self.config.loss, drawn.ssim_reference,
                                       compiled=self.profile.compiled)
                total = total + loss * weight / weight_sum
            for correction in corrections:
                total = total + correction.prior(self.config.poses)
        with self._timed("backward"):
            if total.requires_grad:
                total.backward()
        with self._timed("statistics"):
            for gaussians, output, drawn in renders:
                grad = output.means2d.grad if output.means2d.requires_grad else None
                refine.accumulate(self.anchors, gaussians, grad, output.visible,
                                  drawn.intrinsics.width, drawn.intrinsics.height)
        with self._timed("optimizer"):
            self.optimizer.step()
            if self.hash_optimizer is not None:
                self.hash_optimizer.step()
            self.average.update()
            for correction in corrections:
                correction.step(self.config.poses)
        self.last_gaussians = len(renders[0][0]) if renders else 0
        return total.detach()

    def _moves(self, correction: PoseCorrection | None, view: View) -> bool:
        """Whether a step moves ``correction``: not one held at the client's pose by its tracking, and not
        the view's without ``poses.view_steps`` (the view then keeps the pose its tracking found)."""
        if correction is None or correction.held:
            return False
        return self.config.poses.view_steps or correction is not view.correction

    def _window_weights(self, keyframes: list[Keyframe]) -> list[float]:
        """Loss weights of a step's view and its window ``keyframes``: ``loss.view`` for the view once
        the window is full, else 1, and 1 for each keyframe. Keyframes hold what the map has to keep;
        a streamed view, what the camera sees now (bench/RESULTS.md; commit c6257e9, 2026-11-26)."""
        view = self.config.loss.view if self.keyframes.is_full() else 1.0
        return [view] + [1.0] * len(keyframes)

    def _drawn(self, keyframe: Keyframe) -> View:
        """A drawn keyframe as a view on the device: full size if it is local, else downscaled."""
        if not self.keyframes.is_local(keyframe):
            keyframe = keyframe.downscaled(self._window_scale(keyframe.intrinsics.width))
        return keyframe.view(self.device, compiled=self.profile.compiled)

    def _window_scale(self, width: int) -> float:
        """Scale for a global window keyframe: ``window_scale``, but not below ``window_min_width``
        pixels. The view and local keyframes stay full size: they supervise what the view sees
        (half-size local keyframes cost 1.6 dB on Replica room0 at 600x340, bench/RESULTS.md)."""
        settings = self.config.keyframes
        return min(1.0, max(settings.window_scale, settings.window_min_width / width))

    def _features(self, rows: torch.Tensor) -> torch.Tensor:
        if self.encoding is not None:
            return self.encoding(self.anchors.positions.index_select(0, rows), compiled=self.profile.compiled)
        return self.anchors.features.index_select(0, rows)  # index_add_ backward: faster than [rows]

    def _window_features(self, rows: list[torch.Tensor]) -> Callable[[torch.Tensor], torch.Tensor]:
        """Features for one step's renders of anchors ``rows`` (one tensor per view). The hash grid's
        do not depend on the view, so every anchor the window sees is encoded once, and its gradient
        from all the views goes back through the encoding once (not once per view: a dense step
        renders four views of mostly the same anchors)."""
        if self.encoding is None:
            return self._features
        seen = torch.unique(torch.cat(rows))  # sorted
        encoded = self._features(seen)
        return lambda view_rows: encoded.index_select(0, torch.searchsorted(seen, view_rows))

    def _rows_in_view(self, c2w: torch.Tensor, intrinsics: Intrinsics) -> torch.Tensor:
        return anchors_in_view(self.anchors, intrinsics, c2w, far=self.config.octree.depth_max * 2)

    def _camera(self, c2w: torch.Tensor, intrinsics: Intrinsics) -> Camera:
        return Camera(world_to_camera(c2w), intrinsics_matrix(intrinsics, self.device), intrinsics.width,
                      intrinsics.height)

    def _render(self, c2w: torch.Tensor, intrinsics: Intrinsics) -> tuple[GaussianSet, RenderOutput]:
        """Decode and rasterize the anchors in view."""
        with self._timed("decode"):
            rows = self._rows_in_view(c2w, intrinsics)
            gaussians = generate(self.anchors, self._features, self.decoders, c2w[:3, 3], rows,
                                 compiled=self.profile.compiled)
        with self._timed("rasterize"):
            camera = self._camera(c2w, intrinsics)
            output = rasterize(
                gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities, gaussians.colors,
                camera.viewmat, camera.K, camera.width, camera.height, backend=self.backend,
            )
        return gaussians, output

    # ------------------------------------------------------------------ queries

    def render(self, c2w: np.ndarray, intrinsics: Intrinsics) -> Rendered:
        """Colour, depth and alpha from any pose (camera-to-world) and intrinsics."""
        with on_stream(self.stream):
            pose = torch.as_tensor(np.asarray(c2w), dtype=self.profile.precision, device=self.device)
            with self.lock, torch.no_grad(), torch_threads(self.profile.threads), self.average.applied():
                _, output = self._render(pose, intrinsics)
            return Rendered(
                color=output.color.clamp(0, 1).cpu().numpy().astype(np.float32),
                depth=output.depth.cpu().numpy().astype(np.float32),
                alpha=output.alpha.cpu().numpy().astype(np.float32),
            )

    def stats(self) -> MapStats:
        """Map statistics as one consistent record."""
        with on_stream(self.stream), self.lock:
            return MapStats(
                frames=self.frames,
                keyframes=len(self.keyframes),
                iterations=self.iterations,
                anchors=len(self.anchors),
                anchors_per_level=tuple(self.anchors.level_counts(self.config.octree.max_level)),
                gaussians=self.last_gaussians,
                octree_cells_per_level=tuple(self.octree.count(level) for level in range(self.octree.levels)),
                device=str(self.device),
                backend=self.backend,
                timings=self.timings,
                poses=self._pose_summary(),
            )

    def _pose_summary(self) -> PoseSummary | None:
        """Pose refinement over the keyframes' corrections (hold the lock); None without refinement."""
        if not self.config.poses.refine:
            return None
        reports = [keyframe.correction.report(keyframe.c2w) for keyframe in self.keyframes.keyframes
                   if keyframe.correction is not None]
        metres = [report.translation_m for report in reports] or [0.0]
        degrees = [report.rotation_deg for report in reports] or [0.0]
        return PoseSummary(len(reports), float(np.mean(metres)), max(metres), float(np.mean(degrees)), max(degrees),
                           sum(report.clamped for report in reports))

    def keyframe_poses(self) -> list[KeyframePose]:
        """Every keyframe's pose as the client gave it and as refinement has left it so far."""
        with on_stream(self.stream), self.lock:
            poses = []
            for keyframe in self.keyframes.keyframes:
                client = keyframe.c2w.detach().double().cpu().numpy()
                report = keyframe.correction.report(keyframe.c2w) if keyframe.correction is not None else None
                poses.append(KeyframePose(keyframe.index, client, client if report is None else report.refined_c2w,
                                          report is not None and report.clamped))
            return poses

    def decode_at(self, camera_center: np.ndarray, max_anchors: int = 0) -> GaussianSet:
        """Every anchor's Gaussians as seen from ``camera_center`` (colours and opacities depend on
        the viewpoint through the decoders); no frustum culling, no gradients. ``max_anchors`` > 0
        decodes only that many, evenly spread over the map, so a preview costs a bounded time."""
        with on_stream(self.stream):
            center = torch.as_tensor(np.asarray(camera_center), dtype=torch.float32, device=self.device)
            with self.lock, torch.no_grad(), torch_threads(self.profile.threads), self.average.applied():
                count = len(self.anchors)
                stride = -(-count // max_anchors) if max_anchors and count > max_anchors else 1
                rows = torch.arange(0, count, stride, device=self.device)
                gaussians = generate(self.anchors, self._features, self.decoders, center, rows,
                                     compiled=self.profile.compiled)
        handed_out(self.stream, (getattr(gaussians, name.name) for name in fields(gaussians)))
        return gaussians

    def camera_centroid(self) -> np.ndarray | None:
        """Mean camera position of every frame mapped into this map (across snapshots), or None
        for a map that has none on record (an empty one, or a snapshot written before it was kept)."""
        with self.lock:
            if not self.camera_positions:
                return None
            return (self.camera_position_sum / self.camera_positions).numpy()

    def anchor_centroid(self) -> np.ndarray:
        """Mean anchor centre (the origin for an empty map)."""
        with on_stream(self.stream), self.lock:
            if not len(self.anchors):
                return np.zeros(3)
            return self.anchors.positions.mean(0).double().cpu().numpy()

    # ------------------------------------------------------------------ state

    def state(self, training_state: bool = False) -> MapState:
        """The map as plain tensors and counters (see ``ogmapping.persist.state``), detached copies: the map
        that renders (its moving average, ``optim.average_decay``); with ``training_state`` the live
        map instead and what its optimisation carries (``ogmapping.persist.training``, the average included),
        so a mapper rebuilt from it maps on exactly as this one would."""
        with on_stream(self.stream):
            state = self._state(training_state)
        handed_out(self.stream, state.tensors.values())
        return state

    def _state(self, training_state: bool) -> MapState:
        with self.lock, nullcontext() if training_state else self.average.applied():
            anchors = self.anchors
            tensors: dict[str, torch.Tensor] = {
                "anchors.codes": anchors.codes,
                "anchors.levels": anchors.levels,
                "anchors.log_scales": anchors.log_scales,
                "anchors.offsets": anchors.offsets,
                "anchors.spawned": anchors.spawned.to(torch.uint8),
                "anchors.observations": anchors.observations,
            }
            if anchors.with_features:
                tensors["anchors.features"] = anchors.features
            if anchors.with_colours:
                tensors["anchors.colours"] = anchors.colours
            if self.encoding is not None:
                tensors["encoding.table"] = self.encoding.table
            tensors.update({f"decoders.{name}": value for name, value in self.decoders.state_dict().items()})
            tensors.update({f"octree.{name}": value for name, value in self.octree.state_dict().items()})
            tensors["trajectory.camera_position_sum"] = self.camera_position_sum
            tensors["trajectory.camera_positions"] = torch.tensor([self.camera_positions], dtype=torch.int64)
            if self.config.poses.refine:
                tensors.update(self._keyframe_pose_tensors())
            tensors = {name: value.detach().clone() for name, value in tensors.items()}
            if training_state:
                tensors.update(training.capture(self._optimisation()))
            return MapState(self.config, tensors, self.frames, self.iterations)

    def _keyframe_pose_tensors(self) -> dict[str, torch.Tensor]:
        """The keyframes' client and refined poses, so a snapshot keeps what refinement found (a map
        loaded from it does not read them back: they describe its making, not the map)."""
        poses = self.keyframe_poses()
        return {
            "poses.keyframe_indices": training.frame_indices_as_int64([pose.index for pose in poses]),
            "poses.client_c2w": torch.from_numpy(np.array([pose.client_c2w for pose in poses]).reshape(-1, 4, 4)),
            "poses.refined_c2w": torch.from_numpy(np.array([pose.refined_c2w for pose in poses]).reshape(-1, 4, 4)),
        }

    @classmethod
    def from_state(cls, state: MapState, device: str | torch.device = "cpu", training_state: bool = False) -> Mapper:
        """A mapper holding ``state``'s map; mapping can continue from it, with ``training_state``
        from the optimisation state it holds (a server's own checkpoint: never a snapshot from
        outside). ValueError when the tensors do not fit the config (states may come from outside)."""
        mapper = cls(state.config, device)
        handed_in(mapper.stream, state.tensors.values())
        try:
            with on_stream(mapper.stream):
                mapper._load(state)
                if training_state:
                    mapper.last_gaussians = training.restore(mapper._optimisation(), state.tensors) or 0
        except (KeyError, RuntimeError, ValueError) as error:
            raise ValueError(f"map state does not match its config: {error}") from error
        mapper.frames = state.frames
        mapper.iterations = state.iterations
        return mapper

    def _optimisation(self) -> training.Optimisation:
        return training.Optimisation(self.anchors, self.optimizer, self.hash_optimizer, self.generator, self.keyframes,
                                     self.device, self.last_gaussians, self.average)

    def _load(self, state: MapState) -> None:
        self.octree.load_state_dict(state.section("octree"))
        self.octree.device = self.device
        self.decoders.load_state_dict(state.section("decoders"))
        anchors = self.anchors
        count = state.tensors["anchors.codes"].numel()
        n_offsets, feature_dim = anchors.n_offsets, anchors.feature_dim
        tensor = _checked_shapes(state.tensors, {
            "anchors.codes": (count,), "anchors.levels": (count,), "anchors.log_scales": (count, 3),
            "anchors.offsets": (count, n_offsets, 3), "anchors.spawned": (count, n_offsets),
            "anchors.observations": (count,),
            **({"anchors.features": (count, feature_dim)} if anchors.with_features else {}),
            **({"encoding.table": tuple(self.encoding.table.shape)} if self.encoding is not None else {}),
        }, self.device)
        if self.encoding is not None:
            self.encoding.table.data.copy_(tensor["encoding.table"])
        codes, levels = tensor["anchors.codes"], tensor["anchors.levels"]
        features = tensor["anchors.features"] if anchors.with_features else None
        # Snapshots written before anchors had colours hold none: theirs start at zero (the decoder's colour).
        colours = (_checked_shapes(state.tensors, {"anchors.colours": (count, 3)}, self.device)["anchors.colours"]
                   if anchors.with_colours and "anchors.colours" in state.tensors else None)
        anchors.add(codes, levels, self.octree.centers_by_level(codes, levels),
                    torch.ones(count, device=self.device), features, self.optimizer, colours)
        anchors.log_scales.data.copy_(tensor["anchors.log_scales"])
        anchors.offsets.data.copy_(tensor["anchors.offsets"])
        anchors.spawned = tensor["anchors.spawned"].bool()
        anchors.observations = tensor["anchors.observations"]
        if "trajectory.camera_position_sum" in state.tensors:  # absent in snapshots written before it was kept
            trajectory = _checked_shapes(
                state.tensors, {"trajectory.camera_position_sum": (3,), "trajectory.camera_positions": (1,)}, "cpu"
            )
            position_sum = trajectory["trajectory.camera_position_sum"].double()
            positions = int(trajectory["trajectory.camera_positions"][0])
            if not bool(torch.isfinite(position_sum).all()) or positions < 0:
                raise ValueError("trajectory: the camera position sum must be finite and the count non-negative")
            self.camera_position_sum, self.camera_positions = position_sum, positions

    def snapshot(self) -> bytes:
        """The map as safetensors bytes (see ``ogmapping.persist.snapshot``)."""
        return snapshot.encode(self.state())

    @classmethod
    def restore(cls, data: bytes, device: str | torch.device = "cpu", bounds: ConfigBounds | None = None) -> Mapper:
        """A mapper from snapshot bytes; mapping can continue from it. A config beyond ``bounds``
        (a server's) raises ValueError before anything is allocated for it."""
        return cls.from_state(snapshot.decode(data, bounds), device)


def _checked_shapes(
    tensors: dict[str, torch.Tensor], shapes: dict[str, tuple[int, ...]], device: torch.device
) -> dict[str, torch.Tensor]:
    """The named tensors on ``device``, each exactly of its shape: a copy into a parameter would
    otherwise broadcast a tensor that is too small."""
    checked = {}
    for name, shape in shapes.items():
        value = tensors[name]
        if tuple(value.shape) != shape:
            raise ValueError(f"{name} has shape {tuple(value.shape)}, expected {shape}")
        checked[name] = value.to(device)
    return checked
