"""Keyframe insertion by coarse-anchor overlap, and the dynamic keyframe window (paper 3.3).

``keyframes.window`` picks the window (paper table "keyframe window"): ``dynamic`` (the paper's)
draws b1 local and b2 global keyframes afresh every iteration; the fixed windows pick b1 + b2
earlier keyframes once, when a keyframe is inserted, and keep them until the next one:
``random`` (ESLAM), ``overlap`` (the most overlapping with K_new, SplaTAM / MonoGS) and
``coverage`` (greedy coverage of coarse cells K_new does not see, H2-Mapping-like).

The dynamic window's global keyframes are drawn uniformly (``keyframes.global_draw=random``, the
paper's) or as the ``stalest`` ones: those whose last window lies furthest back, so every region of a
long run is revisited in turn.

Keyframes whose poses a client corrected (``revisit``) join every window drawn after it, besides
the keyframes drawn as above, ``REVISIT_PER_DRAW`` at a time in turn until each has joined
``REVISIT_DRAWS`` windows: the map they moved is settled where it moved to.

A frame's footprint is the set of occupied coarsest-level octree cells it sees (``Footprint``, a mask
over the octree's sorted Morton codes, ``SparseVoxelOctree.seen_mask``): each cell is tested once at its
centre's pixel against the measured depth, so the footprint, and with it keyframe insertion, does not
change with the image resolution. Overlaps stay on the device until the host reads them: the keyframe
test with the frame's allocation, an insertion's weights all at once.
"""

from __future__ import annotations

import random
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import torch

from ogmapping.config import KeyframeConfig, Window
from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.preprocess import resize_depth
from ogmapping.optim.exposure import Exposure
from ogmapping.optim.poses import PoseCorrection
from ogmapping.optim.ssim import ReferenceStatistics, reference_statistics
from ogmapping.runtime.host_read import read
from ogmapping.structure.footprint import Footprint, overlap


@dataclass
class View:
    """A frame as the loss reads it: float32 images on the mapper's device and their SSIM statistics."""

    rgb: torch.Tensor  # (H, W, 3) in [0, 1]
    depth: torch.Tensor  # (H, W), metres, 0 = invalid
    intrinsics: Intrinsics
    c2w: torch.Tensor  # (4, 4), the client's pose
    ssim_reference: ReferenceStatistics
    correction: PoseCorrection | None = None  # with ``poses.refine``: the pose's learnable correction
    exposure: Exposure | None = None  # with ``keyframes.exposure``: the render's learnable colour correction

    @classmethod
    def of(cls, rgb: torch.Tensor, depth: torch.Tensor, intrinsics: Intrinsics, c2w: torch.Tensor, *,
           compiled: bool, correction: PoseCorrection | None = None, exposure: Exposure | None = None) -> View:
        """The view of these images; ``compiled`` as ``ssim.reference_statistics``."""
        return cls(rgb, depth, intrinsics, c2w, reference_statistics(rgb, compiled=compiled), correction, exposure)


@dataclass
class Keyframe:
    """A stored keyframe, compact and in host memory: colour as uint8, depth as float16.

    Keyframes accumulate for the whole session. As float32 images with their SSIM statistics, on the
    mapper's device, one took 12.3 MB at 640x480 (15.4 MB with the half-size copy the window draws:
    15 GB of GPU memory per 1000 keyframes); stored like this it takes 1.5 MB (1.9 MB) of host
    memory, and only the drawn window is on the device, as ``View``s made afresh at every draw.
    Pinned when mapping on CUDA, so those copies are asynchronous, and so is the copy off the device
    when it is captured (``ready`` marks its end): the device copies back through ``view`` and
    ``device_depth`` in stream order without waiting; the host reads ``rgb`` and ``depth`` once it is done.
    """

    index: int
    host_rgb: torch.Tensor  # (H, W, 3) uint8, host memory (``rgb`` once it is there)
    host_depth: torch.Tensor  # (H, W) float16 metres, 0 = invalid, host memory (``depth`` once it is there)
    intrinsics: Intrinsics
    c2w: torch.Tensor  # (4, 4), the client's pose, on the mapper's device
    footprint: Footprint  # the occupied coarsest cells this frame sees
    pinned: bool = False
    correction: PoseCorrection | None = None  # with ``poses.refine``, every keyframe's but the first
    ready: torch.cuda.Event | None = None  # recorded after the copy off the device, until the host has waited on it
    exposure: Exposure | None = None  # with ``keyframes.exposure``, every keyframe's but the first
    _downscaled: dict[float, Keyframe] = field(default_factory=dict, repr=False)

    @classmethod
    def capture(cls, index: int, rgb: torch.Tensor, depth: torch.Tensor, intrinsics: Intrinsics,
                c2w: torch.Tensor, footprint: Footprint, *, pinned: bool = False,
                correction: PoseCorrection | None = None, exposure: Exposure | None = None) -> Keyframe:
        """Store float ``rgb`` in [0, 1] (rounded to 1/255: exact for 8-bit images at their own size)
        and ``depth`` in metres (float16: steps of 2 mm from 2 to 4 m, 4 mm from 4 to 8 m) from any device;
        from CUDA into pinned memory without waiting (``ready``)."""
        colour = (rgb.detach() * 255.0).round_().clamp_(0.0, 255.0).to(torch.uint8)
        depth = depth.detach().to(torch.float16)
        if colour.device.type != "cuda":
            return cls(index, _host(colour, pinned), _host(depth, pinned), intrinsics, c2w, footprint, pinned,
                       correction, exposure=exposure)
        host_rgb, host_depth = (torch.empty(t.shape, dtype=t.dtype, pin_memory=True) for t in (colour, depth))
        host_rgb.copy_(colour, non_blocking=True)
        host_depth.copy_(depth, non_blocking=True)
        ready = torch.cuda.Event()
        ready.record()
        return cls(index, host_rgb, host_depth, intrinsics, c2w, footprint, True, correction, ready, exposure)

    @property
    def rgb(self) -> torch.Tensor:
        """The colour on the host, once its copy there is done."""
        self._wait()
        return self.host_rgb

    @property
    def depth(self) -> torch.Tensor:
        """The depth on the host, once its copy there is done."""
        self._wait()
        return self.host_depth

    def _wait(self) -> None:
        if self.ready is not None:
            self.ready.synchronize()
            self.ready = None

    def device_depth(self, device: torch.device) -> torch.Tensor:
        """The depth as float32 on ``device``, copied there in stream order (no wait on the host)."""
        return self.host_depth.to(device, non_blocking=self.pinned).to(torch.float32)

    def device_rgb(self, device: torch.device) -> torch.Tensor:
        """The colour as float32 in [0, 1] on ``device``, copied there in stream order (no wait on the host)."""
        return self.host_rgb.to(device, non_blocking=self.pinned).to(torch.float32) / 255.0

    def view(self, device: torch.device, *, compiled: bool, images: Callable | None = None) -> View:
        """This keyframe as float32 images on ``device`` (copied there now), with SSIM statistics;
        ``images`` is ``view_images`` or its compiled graph (which ``compiled`` then does not apply to)."""
        if images is not None:
            rgb, depth, statistics = images(self.host_rgb.to(device, non_blocking=self.pinned),
                                            self.host_depth.to(device, non_blocking=self.pinned))
            return View(rgb, depth, self.intrinsics, self.c2w, statistics, self.correction, self.exposure)
        return View.of(self.device_rgb(device), self.device_depth(device), self.intrinsics, self.c2w,
                       compiled=compiled, correction=self.correction, exposure=self.exposure)

    def downscaled(self, scale: float) -> Keyframe:
        """This keyframe with its images resized by ``scale`` (colour by area, depth nearest), cached."""
        if scale == 1.0:
            return self
        if scale not in self._downscaled:
            intrinsics = self.intrinsics.scaled(scale)
            size = (intrinsics.width, intrinsics.height)
            rgb = cv2.resize(self.rgb.numpy().astype("float32") / 255.0, size, interpolation=cv2.INTER_AREA)
            depth = torch.from_numpy(resize_depth(self.depth.numpy(), *size))
            self._downscaled[scale] = Keyframe.capture(self.index, torch.from_numpy(rgb), depth, intrinsics,
                                                       self.c2w, self.footprint, pinned=self.pinned,
                                                       correction=self.correction, exposure=self.exposure)
        return self._downscaled[scale]


def view_images(rgb: torch.Tensor, depth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, ReferenceStatistics]:
    """A stored keyframe's uint8 colour and float16 depth (on the device) as float32 images, and the
    colour's SSIM statistics (torch's blur)."""
    rgb = rgb.to(torch.float32) / 255.0
    return rgb, depth.to(torch.float32), reference_statistics(rgb, compiled=False)


def _host(tensor: torch.Tensor, pinned: bool) -> torch.Tensor:
    return tensor.pin_memory() if pinned else tensor


def _count_missing(sorted_codes: torch.Tensor, codes: torch.Tensor) -> int:
    """How many of ``codes`` are not in ``sorted_codes``."""
    if sorted_codes.numel() == 0:
        return int(codes.numel())
    positions = torch.searchsorted(sorted_codes, codes).clamp_max(sorted_codes.numel() - 1)
    return int((sorted_codes[positions] != codes).sum())


# Fixed windows: positions of ``count`` earlier keyframes, chosen once per inserted keyframe from
# the earlier keyframes, the new one and their overlap weights with it.
def random_window(earlier: list[Keyframe], new: Keyframe, weights: list[float], count: int,
                  rng: random.Random) -> list[int]:
    """``count`` earlier keyframes drawn uniformly without replacement (ESLAM)."""
    return rng.sample(range(len(earlier)), min(count, len(earlier)))


def overlap_window(earlier: list[Keyframe], new: Keyframe, weights: list[float], count: int,
                   rng: random.Random) -> list[int]:
    """The ``count`` earlier keyframes overlapping K_new most (ties: the newer), SplaTAM / MonoGS."""
    return sorted(range(len(earlier)), key=lambda position: (-weights[position], -position))[:count]


def coverage_window(earlier: list[Keyframe], new: Keyframe, weights: list[float], count: int,
                    rng: random.Random) -> list[int]:
    """Greedy coverage (H2-Mapping-like): repeatedly the earlier keyframe that sees the most coarse
    cells not yet covered by K_new and the keyframes already picked (ties: the newer)."""
    covered, chosen = new.footprint.codes(), []
    remaining = list(range(len(earlier)))
    for _ in range(min(count, len(earlier))):
        _, best = max((_count_missing(covered, earlier[position].footprint.codes()), position)
                      for position in remaining)
        chosen.append(best)
        remaining.remove(best)
        covered = torch.unique(torch.cat([covered, earlier[best].footprint.codes()]))
    return chosen


# Every value of ``keyframes.window`` but ``dynamic``, and how it chooses.
FIXED_WINDOWS: dict[Window, Callable[[list[Keyframe], Keyframe, list[float], int, random.Random], list[int]]] = {
    "random": random_window, "overlap": overlap_window, "coverage": coverage_window,
}


# Corrected keyframes: how many windows each joins, and at most how many join one window.
REVISIT_DRAWS = 4
REVISIT_PER_DRAW = 2


class KeyframeSet:
    """The keyframes so far, the newest one's local/global split, and window draws.

    With a ``footprint`` (a keyframe's seen cells on the map as it is now), stored footprints are
    refreshed before each comparison, so two views are always compared on the same map: cells a
    keyframe's own depth was too coarse to allocate, but it sees, then count for it too.
    """

    def __init__(self, config: KeyframeConfig, seed: int = 0,
                 footprint: Callable[[Keyframe], Footprint] | None = None) -> None:
        self.config = config
        self.keyframes: list[Keyframe] = []
        self.local: list[int] = []
        self.global_: list[int] = []
        self.random = random.Random(seed)
        self.footprint = footprint
        self.fixed: list[int] = []  # a fixed window's earlier keyframes, chosen when K_new came
        # Corrected keyframes still to join windows: (position, windows left), in turn.
        self.revisits: deque[tuple[int, int]] = deque()
        self.draws = 0  # dynamic windows drawn so far
        self.trained: list[int] = []  # per keyframe, the draw that last put it in a window (-1: none yet)

    def __len__(self) -> int:
        return len(self.keyframes)

    def _refresh(self, keyframes: list[Keyframe]) -> None:
        if self.footprint is not None:
            for keyframe in keyframes:
                keyframe.footprint = self.footprint(keyframe)

    def overlap_with_last(self, footprint: Footprint) -> torch.Tensor:
        """How much a frame's footprint overlaps the last keyframe's (on the device; -1 without keyframes)."""
        if not self.keyframes:
            return torch.full((), -1.0, dtype=torch.float64, device=footprint.seen.device)
        self._refresh(self.keyframes[-1:])
        return overlap(footprint, self.keyframes[-1].footprint)

    def inserts(self, overlap_with_last: float, frame_index: int) -> bool:
        """A frame is a keyframe when it overlaps the last keyframe less than the threshold (any frame, first), or
        comes ``max_gap`` frames or more after it."""
        if overlap_with_last < 0 or overlap_with_last < self.config.overlap_threshold:
            return True
        gap = self.config.max_gap
        return bool(gap) and bool(self.keyframes) and frame_index - self.keyframes[-1].index >= gap

    def insert(self, keyframe: Keyframe) -> None:
        """Add K_new and split the earlier keyframes into local and global sets by overlap weight
        (or, with a fixed window, choose that window once)."""
        self._refresh(self.keyframes)
        self.local, self.global_ = [], []
        weights = read(*(overlap(keyframe.footprint, other.footprint) for other in self.keyframes))
        for position, weight in enumerate(weights):
            (self.local if weight >= self.config.local_threshold else self.global_).append(position)
        if self.config.window != "dynamic":
            choose = FIXED_WINDOWS[self.config.window]
            count = self.config.local_count + self.config.global_count
            self.fixed = choose(self.keyframes, keyframe, weights, count, self.random)
        self.keyframes.append(keyframe)
        self.trained.append(-1)

    def is_local(self, keyframe: Keyframe) -> bool:
        """Whether ``keyframe`` sees much of what the current view sees: the newest keyframe, or
        one in its local set (overlap weight >= ``local_threshold``)."""
        return keyframe is self.keyframes[-1] or any(keyframe is self.keyframes[i] for i in self.local)

    def revisit(self, positions: list[int]) -> None:
        """Corrected keyframes (positions in the list) join the next windows (``REVISIT_DRAWS`` each)."""
        again = set(positions)
        self.revisits = deque([item for item in self.revisits if item[0] not in again])
        self.revisits.extend((position, REVISIT_DRAWS) for position in positions)

    def _revisiting(self, drawn: list[int]) -> list[int]:
        """The corrected keyframes that join this window (not already in it), each counted as drawn once."""
        joining = []
        for _ in range(min(REVISIT_PER_DRAW, len(self.revisits))):
            position, left = self.revisits.popleft()
            if position not in drawn:
                joining.append(position)
            if left > 1:
                self.revisits.append((position, left - 1))
        return joining

    def _draw_global(self, count: int) -> list[int]:
        """``count`` global keyframes, by ``keyframes.global_draw``."""
        if self.config.global_draw == "random":
            return self.random.sample(self.global_, count)
        return sorted(self.global_, key=lambda position: (self.trained[position], self.random.random()))[:count]

    def window_size(self, view_is_newest: bool) -> int:
        """How many keyframes ``draw_window(view_is_newest)`` returns now (at most: a corrected keyframe
        already drawn does not join twice)."""
        revisiting = min(REVISIT_PER_DRAW, len(self.revisits))
        if self.config.window != "dynamic":
            return len(self.fixed) + revisiting
        local = len(self.local) + (0 if view_is_newest else 1)
        return min(self.config.local_count, local) + min(self.config.global_count, len(self.global_)) + revisiting

    def is_full(self) -> bool:
        """Whether every draw now holds as many global keyframes as the window asks for (a fixed
        window: as many keyframes as it asks for)."""
        if self.config.window != "dynamic":
            return len(self.fixed) >= self.config.local_count + self.config.global_count
        return len(self.global_) >= self.config.global_count

    def draw_window(self, view_is_newest: bool) -> list[Keyframe]:
        """The keyframes trained beside the view: b1 local and b2 global ones drawn afresh without
        replacement, and the corrected keyframes whose turn it is (``revisit``).

        The view is K_new (``view_is_newest``), or a streamed frame that is not a keyframe: it
        overlaps the newest keyframe by at least the insertion threshold, so that keyframe joins the
        local set. With a fixed window, the b1 + b2 keyframes chosen when the newest keyframe was
        inserted, the same at every draw until the next keyframe.
        """
        if self.config.window != "dynamic":
            drawn = list(self.fixed)
        else:
            newest = len(self.keyframes) - 1
            local_set = self.local if view_is_newest else [*self.local, newest]
            drawn = self.random.sample(local_set, min(self.config.local_count, len(local_set)))
            drawn += self._draw_global(min(self.config.global_count, len(self.global_)))
            self.draws += 1
            for position in drawn:
                self.trained[position] = self.draws
        return [self.keyframes[i] for i in drawn + self._revisiting(drawn)]
