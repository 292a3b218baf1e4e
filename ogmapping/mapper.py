"""The online mapper: frames in, an optimised anchor map out (its place in the data flow: docs/architecture.md).

process(frame): register depth, allocate coarse anchors for newly observed space, decide whether
the frame is a keyframe, and if so optimise k iterations, each on a freshly drawn keyframe
window, growing and pruning anchors every m iterations.

The parts it runs: the map itself (``ogmapping.mapping.model``), the tracker that corrects a frame's
pose first (``ogmapping.mapping.tracker``), the mapping steps (``ogmapping.mapping.steps``), what the
map answers (``ogmapping.queries``) and how it is kept (``ogmapping.persist.map_io``).

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
from dataclasses import dataclass, fields

import numpy as np
import torch

from ogmapping import queries
from ogmapping.config import ConfigBounds, MapperConfig, resolution
from ogmapping.frames.camera import Intrinsics, validate_pose
from ogmapping.frames.frame import Frame
from ogmapping.mapping import corrections
from ogmapping.mapping.model import MapModel
from ogmapping.mapping.prepared import PreparedFrame, prepare_on_device, prepare_on_host
from ogmapping.mapping.steps import MappingSteps
from ogmapping.mapping.tracker import Tracker
from ogmapping.model.gaussians import GaussianSet
from ogmapping.optim.exposure import Exposure, stepped
from ogmapping.optim.keyframes import Keyframe, KeyframeSet, View
from ogmapping.optim.poses import PoseCorrection, PoseReport
from ogmapping.persist import map_io, snapshot
from ogmapping.persist.state import MapState
from ogmapping.queries import KeyframePose, Rendered
from ogmapping.runtime.host_read import read
from ogmapping.runtime.late_value import LateValue
from ogmapping.runtime.profile import ExecutionProfile, execution_profile
from ogmapping.runtime.stage_timer import StageTimer
from ogmapping.runtime.streams import handed_in, handed_out, on_stream, session_stream
from ogmapping.runtime.threads import torch_threads
from ogmapping.runtime.time_budget import Budget, Stop
from ogmapping.stats import MapStats
from ogmapping.structure import allocation, extent
from ogmapping.structure.footprint import Footprint


@dataclass
class FrameResult:
    index: int
    keyframe: bool
    anchors: int
    iterations: int
    new_anchors: int
    seconds: float
    # Read from the device when asked for, so the mapper queues the frame's work without waiting for it.
    late_gaussians: LateValue  # Gaussians the frame's last step drew
    late_loss: LateValue  # the frame's last loss (NaN without steps)
    stopped: Stop | None = None  # why optimisation ended before ``iterations`` reached the planned count
    pose: PoseReport | None = None  # the frame's pose after its steps (``poses.refine``; else the client's)

    @property
    def gaussians(self) -> int:
        return int(self.late_gaussians.value())

    @property
    def loss(self) -> float:
        return float(self.late_loss.value())


class Mapper:
    """One session's map and the optimisation that builds it."""

    def __init__(self, config: MapperConfig, device: str | torch.device = "cpu",
                 bounds: ConfigBounds | None = None) -> None:
        """``bounds`` (a server's) also hold what the first frame's resolution rules make of the config."""
        # A copy: the first frame may resolve values that depend on its resolution (``_fit_to``).
        config = copy.deepcopy(config)
        self.bounds = bounds
        profile = execution_profile(device, config.backend, config.model.encoding, config.step)
        self.stream = session_stream(profile.device)
        self.preparing = session_stream(profile.device)  # frames prepared on the device (``mapping.prepared``)
        self.lock = threading.RLock()
        self.timer = StageTimer.for_device(profile.device)
        # Each session draws from its own generator: sessions mapping side by side in one server
        # would otherwise interleave draws from torch's global one (and reseed it for each other).
        generator = torch.Generator().manual_seed(config.seed)
        with on_stream(self.stream):
            self.model = MapModel(config, profile, generator, self.timer)
        self.keyframes = KeyframeSet(config.keyframes, config.seed, self._footprint)
        self.tracker = Tracker(self.model, self.lock)
        self.steps = MappingSteps(self.model, self.keyframes, self.lock)
        # A snapshot keeps its keyframes' client and refined poses, not the keyframes: a map loaded from one
        # answers renders at client poses with these until it maps keyframes of its own.
        self.recorded_poses: list[KeyframePose] = []

    @property
    def config(self) -> MapperConfig:
        return self.model.config

    @property
    def profile(self) -> ExecutionProfile:
        return self.model.profile

    @property
    def device(self) -> torch.device:
        return self.profile.device

    @property
    def timings(self) -> dict[str, float]:
        """Seconds per stage so far (``StageTimer``; on CUDA, reading them waits for the device)."""
        return self.timer.totals()

    # ------------------------------------------------------------------ mapping

    def prepare(self, frame: Frame) -> PreparedFrame:
        """``frame`` made ready to map (``ogmapping.mapping.prepared``): on the host, or uploaded and prepared on
        the device (``ExecutionProfile.device_frames``). Touches no map state, so any thread may run it while
        this mapper maps the previous frame (``process`` takes the result): its host time then goes to the stage
        ``preprocess_ahead``, off the mapping thread; ``process`` of a plain frame prepares it itself, in the
        stage ``preprocess``."""
        settings = self.config.octree
        if self.profile.device_frames:
            return prepare_on_device(frame, settings.depth_min, settings.depth_max, self.profile, self.preparing)
        return prepare_on_host(frame, settings.depth_min, settings.depth_max, self.profile)

    def process(self, frame: Frame | PreparedFrame, budget: Budget | None = None) -> FrameResult:
        """Map one frame (plain, or from ``prepare``); returns what happened to it. Optimisation ends early
        once ``budget`` says stop."""
        with on_stream(self.stream), torch_threads(self.profile.threads):
            return self._process(frame, budget or Budget())

    def _process(self, frame: Frame | PreparedFrame, budget: Budget) -> FrameResult:
        start = time.perf_counter()
        model = self.model
        if isinstance(frame, PreparedFrame):
            model.timer.add("preprocess_ahead", frame.seconds)
            prepared = frame
        else:
            with model.timed("preprocess"):
                prepared = self.prepare(frame)
        frame = prepared.given  # its pose, intrinsics and index: the prepared depth is in ``prepared.depth``
        with model.timed("upload"):
            self._fit_to(frame.color_intrinsics)
            prepared.wait_on(self.stream)
            rgb, depth, c2w = model.upload(prepared.rgb, prepared.depth, prepared.c2w)
        # With ``poses.refine`` every frame but the first keyframe's carries a correction of its client pose
        # (the first keeps it: the map stays in the client's frame), tracked against the map before this
        # frame adds to it; the frame is placed at the tracked pose, and its steps refine it further.
        # With ``poses.tracked`` keyframes only a frame that becomes one is tracked, once it is known to be one.
        correction = PoseCorrection(self.device, c2w.dtype) if self.config.poses.refine and self.keyframes else None
        tracks_every = self.config.poses.tracked == "every"
        placed = c2w
        if correction is not None and tracks_every:
            self.tracker.track(frame.color_intrinsics, (rgb, depth, c2w), correction, budget, start)
            placed = correction.refined(c2w).detach()
        # With ``keyframes.exposure`` it carries an exposure too (but the first keyframe), learned in its steps.
        exposure = Exposure(self.device) if self.config.keyframes.exposure and self.keyframes else None
        # The host reads the device once before the steps: how many coarse cells the frame adds, with its
        # keyframe test (the octree stays padded in between, so all of it holds the lock).
        with self.lock:
            with model.timed("allocate"):
                settings = self.config.octree
                extent.check_frame(frame.c2w, frame.color_intrinsics, settings)
                stride = allocation.allocation_stride(settings, frame.color_intrinsics)
                sampled = allocation.sampled_depth(settings, depth, frame.color_intrinsics)
                cells = allocation.allocate(settings.allocation, model.octree, sampled, frame.color_intrinsics, placed,
                                            lambda: model.render(placed, frame.color_intrinsics)[1], stride,
                                            unread=model.profile.static_shapes)
            with model.timed("keyframes"):
                keys = model.octree.keys(0)
                seen = model.octree.seen_mask(keys, depth, frame.color_intrinsics, placed)
                added, overlap = read(cells.count, self.keyframes.overlap_with_last(Footprint(keys, seen)))
            with model.timed("allocate"):
                new_codes = cells.settle(model.octree, int(added))
                first_new = len(model.anchors)
                model.add_coarse_anchors(new_codes, rgb, depth, frame.color_intrinsics, placed, len(self.keyframes) - 1)
        with model.timed("keyframes"):
            is_keyframe = self.keyframes.inserts(overlap, frame.index)
            iterations = self.config.keyframes.step_multiple * self.iterations_for(is_keyframe)
            if is_keyframe:
                footprint = Footprint(model.octree.keys(0), seen[: model.octree.count(0)])
                self.keyframes.insert(Keyframe.capture(frame.index, rgb, depth, frame.color_intrinsics, c2w, footprint,
                                                       pinned=self.device.type == "cuda", correction=correction,
                                                       exposure=exposure))
                with self.lock:  # the anchors this frame allocated belong to it, not to the keyframe before
                    model.anchors.keyframe[first_new:] = len(self.keyframes) - 1
                if correction is not None and not tracks_every:
                    self.tracker.track(frame.color_intrinsics, (rgb, depth, c2w), correction, budget, start,
                                       rows_below=first_new)
        # The frame itself, at full precision, is the view every step trains on.
        view = (View.of(rgb, depth, frame.color_intrinsics, c2w, compiled=self.profile.compiled, correction=correction,
                        exposure=exposure)
                if iterations else None)
        # A keyframe's exposure stays in the optimiser; a streamed frame's leaves it with its steps.
        with stepped(model.optimizer, exposure, is_keyframe, self.lock):
            loss, grown, done, stopped = self.steps.run(iterations, view, is_keyframe, budget, start)
        with self.lock:
            pose = correction.report(c2w) if correction is not None else PoseReport.unrefined(frame.c2w)
        if budget.stop(start) is None:  # a frame out of time leaves the review to the next
            self._review_correction(lambda: budget.stop(start) is not None)
        model.count_frame(frame.c2w)
        return FrameResult(
            index=frame.index,
            keyframe=is_keyframe,
            anchors=len(model.anchors),
            iterations=done,
            new_anchors=int(new_codes.numel()) + grown,
            seconds=time.perf_counter() - start,
            late_gaussians=model.drawn.snapshot(),
            late_loss=LateValue.of(loss),
            stopped=stopped,
            pose=pose,
        )

    def _review_correction(self, stop: Callable[[], bool]) -> None:
        """With ``poses.review``, review one keyframe's correction (``Tracker.review``), each in turn by the count of
        frames mapped (so a resumed map reviews the one it would have), none held at the client's pose."""
        live = self.keyframes.keyframes
        if not self.config.poses.review or len(live) < 2:
            return
        keyframe = live[1 + self.model.frames % (len(live) - 1)]
        if keyframe.correction is None or keyframe.correction.held:  # none without ``poses.refine``
            return
        tensors = (keyframe.device_rgb(self.device), keyframe.device_depth(self.device), keyframe.c2w)
        self.tracker.review(keyframe.intrinsics, tensors, keyframe.correction, stop)

    def _fit_to(self, intrinsics: Intrinsics) -> None:
        """While the config's resolution rules are pending (until its first frame), resolve them for the step
        multiple of ``intrinsics`` (``ogmapping.config.resolution``); a model whose shape changes is rebuilt
        (still empty: a map with anchors never loads with such rules pending), drawn afresh from the seed."""
        if not resolution.pending(self.config):
            return
        multiple = resolution.step_multiple(self.config.resolution.reference_pixels, intrinsics.width,
                                            intrinsics.height)
        resolved = resolution.resolve(self.config, multiple, self.bounds.caps(self.config) if self.bounds else None)
        model = self.model
        self.keyframes.config = resolved.config.keyframes
        with self.lock:
            if resolved.reshaped:
                model.generator.manual_seed(resolved.config.seed)
                model.build(resolved.config)
                return
            model.config = resolved.config
            if resolved.restarts_average:
                model.restart_average()

    def _footprint(self, keyframe: Keyframe) -> Footprint:
        """``keyframe``'s footprint on the map as it is now."""
        depth = keyframe.device_depth(self.device)
        keys = self.model.octree.keys(0)
        return Footprint(keys, self.model.octree.seen_mask(keys, depth, keyframe.intrinsics, keyframe.c2w))

    def iterations_for(self, is_keyframe: bool) -> int:
        """k for a keyframe (more for the very first), ``frame_iterations`` for any other frame, but
        no more than ``frame_renders`` renders of the view and its window (at least one step); the
        frame then gets ``keyframes.step_multiple`` times this (set by the image's resolution).

        The cap bounds a streamed frame's cost as the window fills: with ``frame_renders`` 4 a frame
        with a full window (the view, a local and two global keyframes) takes one step, a frame whose
        only window keyframe is the newest takes two (bench/RESULTS.md "Keyframes and the window")."""
        settings = self.config.keyframes
        if is_keyframe:
            return settings.first_iterations if not self.keyframes else settings.iterations
        if not self.keyframes or settings.frame_iterations == 0:
            return 0
        if settings.frame_renders == 0:
            return settings.frame_iterations
        renders_per_step = 1 + self.keyframes.window_size(view_is_newest=False)
        return min(settings.frame_iterations, max(1, settings.frame_renders // renders_per_step))

    def correct_poses(self, corrected: dict[int, np.ndarray]) -> corrections.Moved:
        """Corrected camera-to-world poses (4x4) of keyframes, by their position in the keyframe list: each
        keyframe's anchors move rigidly with it (``ogmapping.mapping.corrections``), its pose becomes the
        corrected one and it joins the next windows. All or nothing: ValueError, and the map unchanged, for an
        unknown keyframe, a pose that is not rigid, or a move beyond the octree's range."""
        with on_stream(self.stream), self.lock, torch_threads(self.profile.threads):
            deltas = {}
            for position, c2w in corrected.items():
                if not 0 <= position < len(self.keyframes):
                    raise ValueError(f"keyframe {position}: the map has {len(self.keyframes)} keyframes")
                c2w = validate_pose(c2w, f"keyframe {position}: the corrected pose")
                old = self.keyframes.keyframes[position].c2w.detach().cpu().double().numpy()
                deltas[position] = corrections.delta(old, c2w)
            anchors = corrections.move(self.model, deltas)
            for position, c2w in corrected.items():
                pose = self.keyframes.keyframes[position].c2w
                pose.copy_(torch.as_tensor(c2w, dtype=pose.dtype))
            self.keyframes.revisit(list(corrected))
            return corrections.Moved(len(corrected), anchors)

    # ------------------------------------------------------------------ queries

    def render(self, c2w: np.ndarray, intrinsics: Intrinsics, keyframe: int | None = None) -> Rendered:
        """Colour, depth and alpha from any pose (camera-to-world) and intrinsics (``queries.render``). The
        pose is in the map's frame; with ``keyframe`` (a position in ``keyframe_poses``, as ``nearest_keyframe``
        gives) it is a client pose from around that keyframe's time, moved first as refinement moved the
        keyframe (``queries.in_map_frame``; the same pose without ``poses.refine``). ValueError for a keyframe
        the map does not have."""
        with on_stream(self.stream), self.lock, torch_threads(self.profile.threads):
            if keyframe is not None:
                c2w = queries.in_map_frame(self._keyframe_pose(keyframe), c2w)
            return queries.render(self.model, c2w, intrinsics)

    def nearest_keyframe(self, frame_index: int) -> int | None:
        """The position of the keyframe nearest ``frame_index`` (``Frame.index``), None while there is none."""
        with self.lock:
            live = self.keyframes.keyframes
            indices = [keyframe.index for keyframe in live] if live else [pose.index for pose in self.recorded_poses]
            return queries.nearest(indices, frame_index)

    def _keyframe_pose(self, position: int) -> KeyframePose:
        count = len(self.keyframes) or len(self.recorded_poses)
        if not 0 <= position < count:
            raise ValueError(f"keyframe {position}: the map has {count} keyframes")
        if self.keyframes:
            return queries.keyframe_pose(self.keyframes.keyframes[position])
        return self.recorded_poses[position]

    def stats(self) -> MapStats:
        """Map statistics as one consistent record."""
        with on_stream(self.stream), self.lock:
            return queries.map_stats(self.model, self.keyframes)

    def keyframe_poses(self) -> list[KeyframePose]:
        """Every keyframe's pose as the client gave it and as refinement has left it so far; for a map loaded
        from a snapshot, until it maps a keyframe of its own, the poses the snapshot recorded
        (``recorded_poses``)."""
        with on_stream(self.stream), self.lock:
            return queries.keyframe_poses(self.keyframes) if self.keyframes else list(self.recorded_poses)

    def decode_at(self, camera_center: np.ndarray, max_anchors: int = 0) -> GaussianSet:
        """Every anchor's Gaussians as seen from ``camera_center`` (``queries.decode_all``)."""
        with on_stream(self.stream), self.lock, torch_threads(self.profile.threads):
            gaussians = queries.decode_all(self.model, camera_center, max_anchors)
        handed_out(self.stream, (getattr(gaussians, name.name) for name in fields(gaussians)))
        return gaussians

    def camera_centroid(self) -> np.ndarray | None:
        """Mean camera position of every frame mapped into this map, or None where none is on record."""
        with self.lock:
            return queries.camera_centroid(self.model)

    def anchor_centroid(self) -> np.ndarray:
        """Mean anchor centre (the origin for an empty map)."""
        with on_stream(self.stream), self.lock:
            return queries.anchor_centroid(self.model)

    # ------------------------------------------------------------------ state

    def state(self, training_state: bool = False) -> MapState:
        """The map as plain tensors and counters (see ``ogmapping.persist.state``), detached copies: the map
        that renders (its moving average, ``optim.average_decay``); with ``training_state`` the live
        map instead and what its optimisation carries (``ogmapping.persist.training``, the average included),
        so a mapper rebuilt from it maps on exactly as this one would."""
        with on_stream(self.stream), self.lock:
            state = map_io.capture(self.model, self.keyframes, training_state)
        handed_out(self.stream, state.tensors.values())
        return state

    @classmethod
    def from_state(cls, state: MapState, device: str | torch.device = "cpu", training_state: bool = False,
                   bounds: ConfigBounds | None = None) -> Mapper:
        """A mapper holding ``state``'s map; mapping can continue from it, with ``training_state``
        from the optimisation state it holds (a server's own checkpoint: never a snapshot from
        outside). ValueError when the tensors do not fit the config (states may come from outside)."""
        mapper = cls(state.config, device, bounds)
        handed_in(mapper.stream, state.tensors.values())
        with on_stream(mapper.stream):
            map_io.load(mapper.model, mapper.keyframes, state, training_state)
        if not training_state:
            mapper.recorded_poses = map_io.recorded_keyframe_poses(state)
        return mapper

    def snapshot(self) -> bytes:
        """The map as safetensors bytes (see ``ogmapping.persist.snapshot``)."""
        return snapshot.encode(self.state())

    @classmethod
    def restore(cls, data: bytes, device: str | torch.device = "cpu", bounds: ConfigBounds | None = None) -> Mapper:
        """A mapper from snapshot bytes; mapping can continue from it. A config beyond ``bounds``
        (a server's) raises ValueError before anything is allocated for it."""
        return cls.from_state(snapshot.decode(data, bounds), device, bounds=bounds)
