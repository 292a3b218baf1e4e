"""The config's sections as dataclasses: each field's default, its choices (a ``Literal`` type) or
its range (``ranged``), and why where that is not obvious.

Values the paper does not give follow Scaffold-GS / H2-Mapping, tuned for this engine where noted
(the measurements are in bench/RESULTS.md, under the section named).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Literal

from ogmapping.backends import RasterizerBackend
from ogmapping.config.fields import check, ranged
from ogmapping.config.overrides import assign, flatten
from ogmapping.config.resolution import ResolutionConfig, check_rules
from ogmapping.config.retired import retire

Encoding = Literal["hash", "anchor"]  # the dense version's hash grid, or the sparse version's feature per anchor
AnchorColourStart = Literal["zero", "cell"]
Backend = Literal["auto", RasterizerBackend]
# How a mapping step runs (``ogmapping.runtime.profile``): ``dynamic`` selects what it draws (on the CPU with
# the Numba kernels), ``static`` decodes every anchor row with shapes that do not depend on the map's values,
# ``compiled`` runs those as compiled graphs; ``auto`` is ``compiled`` on CUDA and ``dynamic`` on the CPU.
StepMode = Literal["auto", "dynamic", "static", "compiled"]
# The ablation switches (paper section 4); the first value of each is the paper's method.
Allocation = Literal["octree", "unique", "projection"]  # map densification: the paper's, naive, SplaTAM's
Window = Literal["dynamic", "random", "overlap", "coverage"]  # the paper's, or a fixed window (random: ESLAM's)
GlobalDraw = Literal["random", "stalest"]  # how the dynamic window draws its global keyframes
TrackedFrames = Literal["every", "keyframes"]  # which frames' poses tracking corrects
Growth = Literal["anchor", "error", "none"]  # the paper's progressive growth, Scaffold-GS's error-based, none

MAX_OCTREE_LEVEL = 4
# Pixels per axis between allocation samples: wider than any image samples at most one pixel; beyond int64
# torch's slicing fails.
MAX_ALLOCATION_STRIDE = 1 << 16
MAX_TRACK_STRIDE = MAX_ALLOCATION_STRIDE  # the same bound for tracking's pixel samples
MAX_HASH_LOG2_SIZE = 30  # 2^30 rows per level: far beyond any bound a server grants, short of int64 trouble
MAX_HASH_RESOLUTION = 1e4  # cells per metre (0.1 mm cells); hashed corner coordinates stay far inside int64
# Loss weights and learning rates: beyond these the float32 optimisation overflows into NaN or throws
# Gaussians kilometres per step (Adam's steps are about the learning rate in size).
MAX_LOSS_WEIGHT = 1e3
MAX_LEARNING_RATE = 1.0
SEED_RANGE = (-(1 << 63), (1 << 64) - 1)  # what torch.Generator.manual_seed accepts


def _weight(default: float) -> Any:
    return ranged(default, 0, MAX_LOSS_WEIGHT)


def _learning_rate(default: float) -> Any:
    return ranged(default, 0, MAX_LEARNING_RATE)


@dataclass
class ModelConfig:
    encoding: Encoding = "hash"
    n_offsets: int = ranged(5, 1)  # Scaffold-GS uses 10; 5 renders as well here at half the cost
    feature_dim: int = ranged(32, 1)
    hidden_dim: int = ranged(32, 1)
    hash_levels: int = ranged(8, 1)
    hash_features_per_level: int = ranged(4, 1)
    hash_log2_size: int = ranged(19, 1, MAX_HASH_LOG2_SIZE)
    # Cells per metre at the coarsest and the finest hash level.
    hash_min_resolution: float = ranged(4.0, 0, MAX_HASH_RESOLUTION, open_low=True)
    hash_max_resolution: float = ranged(128.0, 0, MAX_HASH_RESOLUTION, open_low=True)
    # A learnable colour logit per anchor, added to the colour decoder's logits for its n Gaussians (not in
    # the paper): a direct, fast-learning colour next to the shared decoder ("Anchor colours").
    anchor_colour: bool = True
    # Where a new anchor's colour starts: "zero" (the decoder's colour), or "cell", the mean colour of the
    # allocating frame's depth points in its cell, which gains on Replica but loses on 7-Scenes, whose colour
    # and depth cameras are not registered ("Anchor colours").
    anchor_colour_start: AnchorColourStart = "zero"
    # The share of the map's first Gaussians that start visible: the opacity decoder's output bias is shifted
    # per slot to that quantile of the first anchors' logits. 0 keeps nn.Linear's random start (the paper's),
    # under which the share is a lottery of the seed ("Visible start").
    initial_visible: float = ranged(0.0, 0, 1)


@dataclass
class OctreeConfig:
    voxel_size: float = ranged(0.1, 0, open_low=True)  # gamma_0, metres: the coarsest anchor level
    max_level: int = ranged(2, 0, MAX_OCTREE_LEVEL)  # finest anchor level; gamma_{l+1} = gamma_l / 4
    depth_min: float = ranged(0.1, 0)
    depth_max: float = ranged(5.0, "depth_min", open_low=True)
    # Back-project every n-th pixel per axis when allocating; 0: by resolution.
    allocation_stride: int = ranged(0, 0, MAX_ALLOCATION_STRIDE)
    allocation: Allocation = "octree"


@dataclass
class KeyframeConfig:
    # A frame becomes a keyframe when N_overlap / N_union is below this.
    overlap_threshold: float = ranged(0.8, 0, 1, open_low=True)
    # A frame this many frames (by index) after the last keyframe becomes one whatever its overlap: a camera
    # that dwells on one view (turning slowly, standing) still leaves keyframes there, whose poses the window
    # refines and whose views it revisits. 0: overlap alone, as the paper. At 15 in ``sparse``: +0.16 / +0.28
    # dB held out on 7-Scenes 0-299 / 300-599, but Replica room0 0-19 at 1200x680 lost 7.5 dB ("A whole run").
    max_gap: int = ranged(0, 0)
    local_threshold: float = ranged(0.3, 0, 1)  # rho_w: keyframes overlapping K_new at least this much are "local"
    local_count: int = ranged(1, 0)  # b1
    global_count: int = ranged(1, 0)  # b2
    iterations: int = ranged(15, 0)  # k: optimisation iterations per new keyframe
    first_iterations: int = ranged(60, 0)  # iterations on the very first keyframe
    frame_iterations: int = ranged(2, 0)  # iterations on a streamed frame that is not a keyframe (window around it)
    # Caps those steps at this many renders (view + window each), at least one; 0: no cap.
    frame_renders: int = ranged(0, 0)
    # Image scale for the window's global keyframes (the view and local ones: full)...
    window_scale: float = ranged(1.0, 0, 1, open_low=True)
    window_min_width: int = ranged(160, 1)  # ...but never narrower than this many pixels (or the keyframe itself)
    window: Window = "dynamic"
    # The dynamic window's b2 global keyframes: ``random`` draws them uniformly without replacement (the
    # paper's); ``stalest`` takes those trained longest ago (ties at random), so every region is revisited
    # in turn instead of by chance ("A whole run").
    global_draw: GlobalDraw = "random"
    # The four step counts above (iterations, first_iterations, frame_iterations, frame_renders) are
    # multiplied by this; ``resolution.steps`` sets it from the first frame's size ("Steps by resolution").
    step_multiple: int = ranged(1, 1)
    # Per-keyframe exposure (not in the paper; MonoGS): each keyframe but the first, and the streamed view
    # in its steps, learns an affine colour correction of its render, exp(a) * colour + b, with the map
    # (``ogmapping.optim.exposure``), so views whose auto-exposure differs do not rewrite each other's
    # surfaces. The first keyframe's is the identity: the map keeps its colour scale, and every render a
    # client sees is uncorrected. Off: on 7-Scenes 0-299 the affine-fit score holds and the raw one falls by
    # 2 dB, the map's colour scale drifting with the exposures ("A whole run").
    exposure: bool = False


@dataclass
class RefineConfig:
    interval: int = ranged(10, 1)  # m: grow and prune every m iterations
    # tau_0 on the mean screen-space gradient (NDC units, as 3DGS and Scaffold-GS).
    grad_threshold: float = ranged(0.0002, 0)
    min_observations: int = ranged(3, 0)  # a Gaussian's gradient is trusted after this many renders
    # rho: an anchor whose Gaussians all stay below it is removed.
    prune_opacity: float = ranged(0.01, 0, 1, open_high=True)
    prune_min_observations: int = ranged(10, 0)  # anchors seen fewer times are never pruned
    max_new_anchors: int = ranged(20000, 0)  # cap per growth step, keeps one step bounded
    growth: Growth = "anchor"


@dataclass
class LossConfig:
    color: float = _weight(0.8)
    ssim: float = _weight(0.2)
    depth: float = _weight(0.5)
    scale: float = _weight(0.01)
    # Weight of a step's view (the streamed frame or the new keyframe) in its loss against each window
    # keyframe's 1, once the window is full (it draws all its global keyframes); before, 1 like them.
    # It divides the step's loss, which a view alone would make 0 / 0 at 0.
    view: float = ranged(1.0, 0, MAX_LOSS_WEIGHT, open_low=True)


@dataclass
class OptimConfig:
    # Four times Scaffold-GS's rates: it trains for 30k iterations, an online map gets a few per frame
    # ("Learning rates").
    offsets_lr: float = _learning_rate(0.04)
    features_lr: float = _learning_rate(0.03)
    scaling_lr: float = _learning_rate(0.028)
    hash_lr: float = _learning_rate(0.01)
    opacity_mlp_lr: float = _learning_rate(0.008)
    color_mlp_lr: float = _learning_rate(0.032)
    cov_mlp_lr: float = _learning_rate(0.016)
    colour_lr: float = _learning_rate(0.08)  # the anchors' own colour logits (model.anchor_colour)
    exposure_lr: float = _learning_rate(0.01)  # the keyframes' exposure scalars (keyframes.exposure; MonoGS's)
    # Queries see the moving average of the map over its last steps, with this decay per step
    # (ogmapping.optim.averaging); 0: the live map, as the paper. Below 1: at 1 the average never moves.
    average_decay: float = ranged(0.0, 0, 1, open_high=True)
    # The average's horizon grows with the map: it covers max(1 / (1 - average_decay), average_growth x
    # steps so far) steps, so an old map averages longer than a young one still converging; 0: fixed.
    average_growth: float = ranged(0.0, 0, 1)
    # Adam steps only the anchor rows the step's views saw (a Gaussian of theirs visible), leaving the others'
    # values and moments as they were (Taming 3DGS's selective Adam; ``ogmapping.optim.selective_adam``):
    # torch's Adam decays every row's moments and moves it by its momentum even where the step gave it no
    # gradient. The decoders and the exposures step as before; the hash grid's lazy Adam already steps only
    # its touched rows. Off: +0.06 dB held out on 7-Scenes 0-299, -0.05 on 300-599 (seed 0), within the seeds' spread
    # (bench/RESULTS.md "A whole run"); its GPU speed in bench/gpu/raster_options.py.
    selective: bool = False
    # Adam's second-moment decay for the map (torch's 0.999 remembers some thousand steps). An anchor seen
    # again after hundreds of steps is still divided by the squared gradients of its first steps and of the
    # frames that disagreed with it, so it learns slowly where the camera returns; ``sparse`` takes 0.99
    # ("Adam's memory").
    second_moment_decay: float = ranged(0.999, 0, 1, open_high=True)


@dataclass
class PosesConfig:
    # Refine each keyframe's and the streamed view's client pose against the map, in the mapping
    # steps (ogmapping.optim.poses); the first keyframe stays fixed, so the map keeps the client's frame.
    # Off by default, on in ``sparse`` (keyframe poses alone, refined in the window: "Keyframe poses refined
    # in the window", "Corrections reviewed"). With every frame tracked, on Replica room0 it gains where poses
    # are noisy and costs a little where they are exact ("Pose refinement").
    refine: bool = False
    # Gradient-descent rates: metres and radians per unit of the loss's gradient (a rotation moves a point
    # about its depth, some 2 m here, times as far: hence the smaller rate).
    translation_lr: float = _learning_rate(0.004)
    rotation_lr: float = _learning_rate(0.001)
    # Mapping steps move a correction at this share of the rates above (tracking steps at the rates
    # themselves): a mapping step's gradient is larger than a tracking step's, and at the full rates a
    # keyframe's correction overshoots by a centimetre a step, both ways ("Keyframe poses refined in the window").
    mapping_rate: float = ranged(1.0, 0, 1)
    # Gradient steps on the frame's pose alone, against the map as it stands, before its mapping steps: a
    # few mapping steps move a pose little, and meanwhile pull the map towards the pose's error. Two are
    # what ``track_min_gain`` needs to tell a pose that moves from one held; the Gauss-Newton steps below
    # take a pose that moves further than more gradient steps would ("Pose refinement").
    track_iterations: int = ranged(2, 0)
    # Which frames are tracked: every frame, before it adds to the map, or only a frame that becomes a
    # keyframe, against the anchors the map held before it (its tracking then gates its correction: one that
    # ``track_min_gain`` holds stays at the client's pose in every window that draws it; on 7-Scenes that held
    # most keyframes and lost refinement's gain: "Corrections reviewed").
    tracked: TrackedFrames = "every"
    # ...on every this-many-th pixel of each row and column (2: a quarter of the pixels), rendered at their
    # own centres with the splats blurred as at full size, so the loss is the full-size loss on those
    # pixels, whose minimum lies on the truth; a resized image's lies off it ("What bounds tracking").
    track_stride: int = ranged(2, 1, MAX_TRACK_STRIDE)
    track_alpha: float = ranged(0.99, 0, 1)  # ...whose loss counts the pixels the map covers this fully
    # Then this many Gauss-Newton steps on a pose that moves (none on one held), on the same pixels: each
    # solves for the correction that explains every pixel's residual, where gradient steps crawl along the
    # loss's flat directions; seven renders a step, no backward pass (ogmapping.optim.pose_newton). 0: none.
    track_newton_iterations: int = ranged(4, 0)
    # Then this many steps on every pixel on a pose that moves (none on one held), at ``track_stride``
    # squared times the cost of a step. 0: none.
    track_fine_iterations: int = ranged(0, 0)
    # A frame whose second tracking step lowers its loss by less than this share of the loss it started
    # from keeps its client's pose, held through every later step (its tracking stops there): a right
    # pose's loss falls on the first step, as the pose fits the young map's own error, then stops; a wrong
    # one's keeps falling ("Pose refinement"). 0: every correction moves. Needs two tracking steps.
    track_min_gain: float = ranged(0.02, 0, 1)
    # After each frame's steps one keyframe's correction, each in turn, goes back to the client's pose where that
    # pose fits the keyframe's own image better (``Tracker.review``): a correction caught a few pixels off where
    # the map has settled around the client's pose ("Corrections reviewed").
    review: bool = False
    # Then this many Gauss-Newton steps on the reviewed correction (none on one held), against the map as it
    # stands: a keyframe's correction moves only in the windows that draw it, while the map around it settles
    # under later views; re-tracked in turn, every keyframe keeps fitting the map it supervises ("Keyframes
    # re-tracked in review": one gains 0.4-0.6 dB held out on 7-Scenes, as two do, at some 14% of the speed, but
    # where poses are exact it fits the young map's error: the synthetic scene loses 1.1 dB, up to 5.2 at stride 4).
    # 0: none, as every preset.
    review_newton_iterations: int = ranged(0, 0)
    # ...on every this-many-th pixel of each row and column, from the review's own decode: at 4 a step renders a
    # quarter of the pixels it does at 2 ("Keyframes re-tracked in review").
    review_newton_stride: int = ranged(2, 1, MAX_TRACK_STRIDE)
    # The streamed view's correction moves in its mapping steps too (else only its tracking steps set it;
    # keyframes' corrections move in every step that draws them).
    view_steps: bool = True
    # Weight of the prior that holds a correction near the client's pose: prior x ((|t| / max_translation)^2
    # + (|r| / max_rotation)^2) joins each view's loss. Weak: a pose the gate lets move is wrong, and at 0.1
    # the prior held noisy poses half a centimetre short of where their loss is lowest ("Pose refinement").
    prior: float = _weight(0.01)
    # A correction beyond these is clamped back to them and reported, never silently applied.
    max_translation: float = ranged(0.1, 0, open_low=True)  # metres
    max_rotation: float = ranged(5.0, 0, 180, open_low=True)  # degrees


@dataclass
class RenderConfig:
    """gsplat's rasterizer options (``ogmapping.render.RasterOptions``), each off as every backend renders.
    ``absgrad`` and ``antialiased`` change what is rendered or read, so a map that sets one needs the gsplat
    backend (ValueError when the mapper is made on another); none is measured yet beyond
    bench/gpu/raster_options.py, which times them at 1200x680 on a GPU."""

    # gsplat's packed layout: only the (view, Gaussian) pairs its culling keeps, instead of arrays of every
    # Gaussian per view; less memory where a view sees a small share of the map, the same images. One gsplat
    # call per view then (its packed backward mixes batch entries' gradients), not one per image size. Other
    # backends render the same without it.
    packed: bool = False
    # Growth reads each Gaussian's absolute screen-space gradient (AbsGS: the sum over pixels of the gradient's
    # absolute value) instead of the gradient: gradients of opposite sign no longer cancel over a large
    # Gaussian. Its values are larger, so ``refine.grad_threshold`` grows more at the same value (gsplat's
    # examples use four times the threshold with it).
    absgrad: bool = False
    # gsplat's antialiased projection: each Gaussian's opacity scaled by sqrt(det(S) / det(S + blur I)) of its
    # 2D covariance S (Mip-Splatting), so the blur no longer makes small Gaussians brighter.
    antialiased: bool = False


@dataclass
class MapperConfig:
    model: ModelConfig = field(default_factory=ModelConfig)
    octree: OctreeConfig = field(default_factory=OctreeConfig)
    keyframes: KeyframeConfig = field(default_factory=KeyframeConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    poses: PosesConfig = field(default_factory=PosesConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    # How settings follow the first frame's size (``ogmapping.config.resolution``), resolved then.
    resolution: ResolutionConfig = field(default_factory=ResolutionConfig)
    backend: Backend = "auto"  # on the CPU only "cpu" runs the compiled kernels
    step: StepMode = "auto"
    seed: int = ranged(0, *SEED_RANGE)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> MapperConfig:
        """A stored config (a snapshot's, a checkpoint's), retired keys turned into their successors."""
        flat = retire(flatten(data))
        config = cls()
        apply_overrides(config, flat)
        return config




def apply_overrides(config: MapperConfig, overrides: dict[str, Any]) -> MapperConfig:
    """Set dotted keys (values typed or as text) on ``config`` in place, then ``validate`` it; unknown
    keys, wrong types and values out of range raise ValueError naming the key."""
    assign(config, overrides, "config", text=True)
    validate(config)
    return config


def validate(config: MapperConfig) -> None:
    """Reject values the engine cannot run with, naming the key and its choices or range."""
    check(config, "config")
    check_rules(config)

