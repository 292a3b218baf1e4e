"""The map a mapper builds: its structures (octree, anchors), what decodes them into Gaussians (the
hash grid or the anchors' own features, and the decoders), what optimises them (Adam, the hash
grid's lazy Adam, the moving average), its counters, and the decode-and-rasterize of what a camera
sees.

The mapper drives it (``ogmapping.mapper``), the steps and the tracker train and read it
(``ogmapping.optim``), persistence copies it out and fills it in (``ogmapping.persist.map_io``). It
holds no lock and picks no stream: its callers do.
"""

from __future__ import annotations

from collections.abc import Callable
from contextlib import AbstractContextManager

import numpy as np
import torch

from ogmapping.config import MapperConfig
from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.frame import Frame
from ogmapping.frames.geometry import intrinsics_matrix, world_to_camera
from ogmapping.mapping.graphs import StepGraphs
from ogmapping.model.decoders import Decoders
from ogmapping.model.encoding import HashGridEncoding, feature_dim, initial_anchor_features
from ogmapping.model.gaussians import GaussianSet, anchors_in_view, decoded_logits, generate
from ogmapping.optim import exposure
from ogmapping.optim.averaging import MapAverage
from ogmapping.optim.lazy_adam import LazyAdam
from ogmapping.optim.selective_adam import SelectiveAdam
from ogmapping.render import Camera, RasterOptions, rasterize
from ogmapping.render.output import RenderOutput
from ogmapping.render.rules import COVARIANCE_BLUR
from ogmapping.runtime.late_value import LateValue
from ogmapping.runtime.profile import ExecutionProfile
from ogmapping.runtime.stage_timer import StageTimer
from ogmapping.structure.anchor_colour import cell_colour_logits, colour_sample_stride
from ogmapping.structure.anchors import LEARNABLE, AnchorMap
from ogmapping.structure.octree import SparseVoxelOctree


class MapModel:
    """One session's map, its optimisers and its counters, on the profile's device."""

    def __init__(self, config: MapperConfig, profile: ExecutionProfile, generator: torch.Generator,
                 timer: StageTimer) -> None:
        self.profile = profile
        self.generator = generator
        self.timer = timer
        self.build(config)
        self.frames = 0
        self.iterations = 0
        self.drawn = LateValue()  # Gaussians the newest step drew in its view
        # Sum of the mapped frames' camera centres (float64): their mean is where a .ply export
        # bakes view-dependent colour by default, and it survives snapshots.
        self.camera_position_sum = torch.zeros(3, dtype=torch.float64)
        self.camera_positions = 0

    def build(self, config: MapperConfig) -> None:
        """The map's structures, decoders and optimisers for ``config``, empty, drawn from the generator as it
        stands (on the caller's stream)."""
        self.config = config
        render = config.render
        self.raster_options = RasterOptions(render.packed, render.absgrad, render.antialiased)
        self.raster_options.check(self.backend)  # before anything is built: a clear refusal
        model = config.model
        self.octree = SparseVoxelOctree.from_config(config.octree, self.device)
        self.anchors = AnchorMap(model.n_offsets, model.feature_dim, model.encoding == "anchor", self.device,
                                 with_colours=model.anchor_colour)
        self.encoding = HashGridEncoding(model, self.generator).to(self.device) if model.encoding == "hash" else None
        self.decoders = Decoders(feature_dim(model), model.n_offsets, model.hidden_dim, self.generator)
        self.decoders = self.decoders.to(self.device)
        self.optimizer = self._make_optimizer()
        self.average = MapAverage(self.anchors, self.decoders, config.optim.average_decay, config.optim.average_growth)
        self.graphs = StepGraphs.build(compiled=self.profile.graphs, device=self.device)
        self.hash_optimizer = (LazyAdam(self.encoding.table, self.encoding.gradients, config.optim.hash_lr,
                                        compiled=self.profile.compiled, static_shapes=self.profile.static_shapes)
                               if self.encoding is not None else None)

    def restart_average(self) -> None:
        """A new moving average at the config's decay (the map's values as they are)."""
        optim = self.config.optim
        self.average = MapAverage(self.anchors, self.decoders, optim.average_decay, optim.average_growth)

    def _make_optimizer(self) -> torch.optim.Adam:
        """Adam over the map's parameters, by group; with ``optim.selective`` the anchor rows' groups step
        only the rows a step saw (``SelectiveAdam``)."""
        lr = self.config.optim
        groups = [
            {"params": [self.anchors.parameter("log_scales")], "lr": lr.scaling_lr, "name": "log_scales"},
            {"params": [self.anchors.parameter("offsets")], "lr": lr.offsets_lr, "name": "offsets"},
            {"params": self.decoders.opacity.parameters(), "lr": lr.opacity_mlp_lr, "name": "opacity_mlp"},
            {"params": self.decoders.color.parameters(), "lr": lr.color_mlp_lr, "name": "color_mlp"},
            {"params": self.decoders.cov.parameters(), "lr": lr.cov_mlp_lr, "name": "cov_mlp"},
        ]
        if self.encoding is None:
            groups.append({"params": [self.anchors.parameter("features")], "lr": lr.features_lr, "name": "features"})
        if self.anchors.with_colours:
            groups.append({"params": [self.anchors.parameter("colours")], "lr": lr.colour_lr, "name": "colours"})
        if self.config.keyframes.exposure:  # the views' exposures join and leave it (``optim.exposure``)
            groups.append({"params": [], "lr": lr.exposure_lr, "name": exposure.GROUP})
        # Fused: its step counts stay tensors (torch's loop reads each on the host). Only with static shapes,
        # whose maps are not the CPU's: it rounds otherwise than the loop the CPU's maps were tuned with.
        fused = self.profile.static_shapes or None
        betas = (0.9, self.config.optim.second_moment_decay)
        if self.config.optim.selective:
            return SelectiveAdam(groups, row_groups=LEARNABLE, betas=betas, eps=1e-15, fused=fused)
        return torch.optim.Adam(groups, betas=betas, eps=1e-15, fused=fused)

    @property
    def last_gaussians(self) -> int:
        return int(self.drawn.value())

    @property
    def device(self) -> torch.device:
        return self.profile.device

    @property
    def backend(self) -> str:
        return self.profile.backend

    def timed(self, stage: str) -> AbstractContextManager[None]:
        """Add the block's time to stage ``stage`` of the mapper's timings (``ogmapping.runtime.stage_timer``):
        the host's on the CPU; on CUDA the device's, from events the host never waits for while mapping."""
        return self.timer.stage(stage)

    def tensors(self, frame: Frame) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """A prepared frame's colour, depth and pose on the device, at the mapper's precision."""
        return tuple(torch.as_tensor(array, dtype=self.profile.precision, device=self.device)
                     for array in (frame.rgb, frame.depth, frame.c2w))

    def upload(self, rgb: torch.Tensor, depth: torch.Tensor, c2w: torch.Tensor) -> tuple[
            torch.Tensor, torch.Tensor, torch.Tensor]:
        """A frame's images and pose, already host tensors at the mapper's precision (pinned on CUDA: copied
        without blocking the host), on the device."""
        return tuple(tensor.to(self.device, non_blocking=True) for tensor in (rgb, depth, c2w))

    def count_frame(self, c2w: np.ndarray) -> None:
        """One more frame mapped, seen from the camera pose ``c2w`` (the client's)."""
        self.frames += 1
        self.camera_position_sum += torch.as_tensor(c2w[:3, 3], dtype=torch.float64)
        self.camera_positions += 1

    # ------------------------------------------------------------------ decoding

    def features(self, rows: torch.Tensor) -> torch.Tensor:
        """The decoders' input features of anchors ``rows``: the hash grid's at their centres, or their own."""
        if self.encoding is not None:
            return self.encoding(self.anchors.buffer("positions").index_select(0, rows), compiled=self.profile.compiled)
        return self.anchors.parameter("features").index_select(0, rows)  # index_add_ backward: faster than [rows]

    def window_features(self, rows: list[torch.Tensor]) -> Callable[[torch.Tensor], torch.Tensor]:
        """Features for one step's renders of anchors ``rows`` (one tensor per view). The hash grid's
        do not depend on the view, so every anchor the window sees is encoded once, and its gradient
        from all the views goes back through the encoding once (not once per view: a dense step
        renders four views of mostly the same anchors)."""
        if self.encoding is None:
            return self.features
        seen = torch.unique(torch.cat(rows))  # sorted
        encoded = self.features(seen)
        return lambda view_rows: encoded.index_select(0, torch.searchsorted(seen, view_rows))

    def buffer_features(self) -> torch.Tensor:
        """The decoders' input features of every row of the anchor buffers (``static_gaussians``)."""
        if self.encoding is not None:
            return self.encoding(self.anchors.buffer("positions"), compiled=self.profile.compiled)
        return self.anchors.parameter("features")

    def rows_in_view(self, c2w: torch.Tensor, intrinsics: Intrinsics) -> torch.Tensor:
        """The anchors a camera at ``c2w`` may see (its frustum out to twice the deepest depth kept)."""
        return anchors_in_view(self.anchors, intrinsics, c2w, far=self.far)

    @property
    def far(self) -> float:
        """How far a camera sees anchors: twice the deepest depth kept."""
        return self.config.octree.depth_max * 2

    def camera(self, c2w: torch.Tensor, intrinsics: Intrinsics, blur: float = COVARIANCE_BLUR) -> Camera:
        return self.viewed(world_to_camera(c2w), intrinsics, blur)

    def viewed(self, viewmat: torch.Tensor, intrinsics: Intrinsics, blur: float = COVARIANCE_BLUR) -> Camera:
        """The camera of a world-to-camera ``viewmat``."""
        return Camera(viewmat, intrinsics_matrix(intrinsics, self.device), intrinsics.width, intrinsics.height, blur)

    def decode(self, center: torch.Tensor, rows: torch.Tensor) -> GaussianSet:
        """The Gaussians of anchors ``rows`` as seen from the camera centre ``center``."""
        return generate(self.anchors, self.features, self.decoders, center, rows, compiled=self.profile.compiled)

    def render(self, c2w: torch.Tensor, intrinsics: Intrinsics) -> tuple[GaussianSet, RenderOutput]:
        """Decode and rasterize the anchors in view."""
        with self.timed("decode"):
            gaussians = self.decode(c2w[:3, 3], self.rows_in_view(c2w, intrinsics))
        with self.timed("rasterize"):
            output = rasterize(gaussians, self.camera(c2w, intrinsics), backend=self.backend,
                               options=self.raster_options)
        return gaussians, output

    def decoded_logits(self, positions: torch.Tensor, features: torch.Tensor | None,
                       c2w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The decoders' logits for new anchors at ``positions`` seen from ``c2w``, from their
        ``features`` (the sparse version's) or the hash grid's."""
        with torch.no_grad():
            if features is None:
                features = self.encoding(positions, compiled=self.profile.compiled)
            return decoded_logits(self.decoders, features, positions, c2w[:3, 3])

    # ------------------------------------------------------------------ growth

    def add_coarse_anchors(self, codes: torch.Tensor, rgb: torch.Tensor, depth: torch.Tensor,
                           intrinsics: Intrinsics, c2w: torch.Tensor, keyframe: int = -1) -> None:
        """New coarsest-level anchors for ``codes``, observed in the frame of ``rgb`` and ``depth``
        (with ``anchor_colour_start`` "cell", each starts with the mean colour of the frame's points
        in its cell), belonging to ``keyframe``. The map's very first anchors set the opacity decoder's
        start (``model.initial_visible``)."""
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
            opacity, _, _ = self.decoded_logits(positions, features, c2w)
            self.decoders.start_visible(opacity, self.config.model.initial_visible)
        colours = None
        if self.anchors.with_colours and self.config.model.anchor_colour_start == "cell":
            stride = colour_sample_stride(self.config.octree.voxel_size, self.config.octree.depth_max, intrinsics)
            target, seen = cell_colour_logits(self.octree, codes, rgb, depth, intrinsics, c2w, stride)
            _, decoded, _ = self.decoded_logits(positions, features, c2w)
            colours = torch.where(seen.unsqueeze(1), target - decoded.view(count, -1, 3).mean(1), 0.0)
        self.anchors.add(codes, levels, positions, sizes, features, self.optimizer, colours, keyframe)
