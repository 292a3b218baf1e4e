"""Keyframe insertion by coarse-anchor overlap, and the dynamic keyframe window (paper 3.3).

A frame's footprint is the set of coarsest-level octree cells its depth observes (sorted Morton
codes): occlusion-aware and cheap, as the cells come straight from back-projected depth.
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field

import cv2
import torch

from ogmapping.camera import Intrinsics
from ogmapping.config import KeyframeConfig
from ogmapping.preprocess import resize_depth
from ogmapping.ssim import ReferenceStatistics, reference_statistics


@dataclass
class Keyframe:
    index: int
    rgb: torch.Tensor  # (H, W, 3)
    depth: torch.Tensor  # (H, W), metres, 0 = invalid
    intrinsics: Intrinsics
    c2w: torch.Tensor  # (4, 4)
    codes: torch.Tensor  # sorted unique coarsest-cell codes this frame observes
    ssim_reference: ReferenceStatistics | None = None  # cached SSIM statistics of ``rgb``
    _downscaled: dict[float, Keyframe] = field(default_factory=dict, repr=False)

    def downscaled(self, scale: float) -> Keyframe:
        """This keyframe with its images resized by ``scale`` (colour by area, depth nearest), cached."""
        if scale == 1.0:
            return self
        if scale not in self._downscaled:
            intrinsics = self.intrinsics.scaled(scale)
            size = (intrinsics.width, intrinsics.height)
            rgb = cv2.resize(self.rgb.cpu().numpy(), size, interpolation=cv2.INTER_AREA)
            rgb = torch.as_tensor(rgb, device=self.rgb.device).clamp(0.0, 1.0)
            depth = torch.as_tensor(resize_depth(self.depth.cpu().numpy(), *size), device=self.depth.device)
            self._downscaled[scale] = Keyframe(self.index, rgb, depth, intrinsics, self.c2w, self.codes,
                                               reference_statistics(rgb))
        return self._downscaled[scale]


def overlap_ratio(first: torch.Tensor, second: torch.Tensor) -> float:
    """N_overlap / N_union of two sorted unique code sets."""
    if first.numel() == 0 and second.numel() == 0:
        return 1.0
    if first.numel() == 0 or second.numel() == 0:
        return 0.0
    positions = torch.searchsorted(second, first).clamp_max(second.numel() - 1)
    overlap = int((second[positions] == first).sum())
    return overlap / (first.numel() + second.numel() - overlap)


class KeyframeSet:
    """The keyframes so far, the newest one's local/global split, and window draws."""

    def __init__(self, config: KeyframeConfig, seed: int = 0) -> None:
        self.config = config
        self.keyframes: list[Keyframe] = []
        self.local: list[int] = []
        self.global_: list[int] = []
        self.random = random.Random(seed)

    def __len__(self) -> int:
        return len(self.keyframes)

    def should_insert(self, codes: torch.Tensor) -> bool:
        """A frame is a keyframe when it overlaps the last keyframe less than the threshold."""
        if not self.keyframes:
            return True
        return overlap_ratio(codes, self.keyframes[-1].codes) < self.config.overlap_threshold

    def insert(self, keyframe: Keyframe) -> None:
        """Add K_new and split the earlier keyframes into local and global sets by overlap weight."""
        self.local, self.global_ = [], []
        for position, other in enumerate(self.keyframes):
            weight = overlap_ratio(keyframe.codes, other.codes)
            (self.local if weight >= self.config.local_threshold else self.global_).append(position)
        self.keyframes.append(keyframe)

    def draw_window(self) -> list[Keyframe]:
        """K_new plus b1 local and b2 global keyframes drawn afresh without replacement."""
        newest = self.keyframes[-1]
        local = self.random.sample(self.local, min(self.config.local_count, len(self.local)))
        global_ = self.random.sample(self.global_, min(self.config.global_count, len(self.global_)))
        return [newest] + [self.keyframes[i] for i in local + global_]
