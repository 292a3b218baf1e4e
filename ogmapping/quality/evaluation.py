"""Scoring a map on the streamed and held-out views: one loop for ``ogmap run`` and ``ogclient eval``.

A ``FrameSet`` chooses frames as ``ogmap run`` does (``selection.select``), optionally with the poses
of a trajectory file in place of the data's, and ``evaluate_views`` renders each chosen view through a
render function (the local mapper, or the server) at the pose a function picks (the frame's own by
default, or that of a second, exact trajectory), taken as a client pose of that frame's time (with
``poses.refine`` the map has moved the poses it was given, and the render moves the pose as the nearest
keyframe's was moved), scores it against the frame as the mapper saw it and writes the same previews, so
both commands report comparable numbers. Renders are scored as they are
(``psnr``, raw) and after the frame's own fitted gain and offset (``psnr_affine``: its exposure taken out,
since the map keeps one reference exposure and is never corrected for a view). No torch at import: the metrics
(SSIM and LPIPS run on torch) are loaded when scoring starts, so the client's other commands can share
the frame set and stay light.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import cv2
import numpy as np
from tqdm import tqdm

from ogmapping.config import MapperConfig
from ogmapping.datasets import FrameSource, open_dataset
from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.frame import Frame
from ogmapping.frames.preprocess import prepare, resize_frame
from ogmapping.frames.selection import Selection, select
from ogmapping.frames.trajectory import Trajectory

if TYPE_CHECKING:
    import torch

    from ogmapping.quality.metrics import Lpips

PREVIEW_COUNT = 3  # side-by-side previews per split


class Rendering(Protocol):
    """What scoring reads of a render: colour (H, W, 3) in [0, 1] and depth (H, W) in metres."""

    color: np.ndarray
    depth: np.ndarray


# (c2w, intrinsics, the frame it is judged against) -> rendering: the frame names the time the pose is from
Render = Callable[[np.ndarray, Intrinsics, Frame], Rendering]
Pose = Callable[[Frame], np.ndarray]  # the frame as the mapper saw it -> the c2w to render it at


@dataclass
class FrameSet:
    """A dataset, which of its positions are streamed and held out, the image scale, and ``poses`` to
    give the frames instead of the data's (matched by ``trajectory.frame_key``)."""

    source: FrameSource
    selection: Selection
    scale: float = 1.0
    poses: Trajectory | None = None

    @property
    def positions(self) -> list[int]:
        """Every streamed and held-out position, in source order."""
        return sorted(self.selection.streamed + self.selection.heldout)

    def load(self, position: int) -> Frame:
        frame = self.source[position]
        if self.poses is not None:
            frame = dataclasses.replace(frame, c2w=self.poses.pose_of(frame))
        return resize_frame(frame, self.scale) if self.scale != 1.0 else frame


def open_frames(
    data: str, format: str = "auto", frames: str | None = None, stride: int = 1, scale: float = 1.0,
    **options: Any,
) -> FrameSet:
    source = open_dataset(data, format, **options)
    selection = select(len(source), frames, stride)
    if not selection.streamed:
        raise ValueError("the frame selection leaves no frame to stream")
    return FrameSet(source, selection, scale)


def ground_truth(frame: Frame, config: MapperConfig) -> Frame:
    """The frame as the mapper sees it: depth on the colour grid, clipped to the working range."""
    return prepare(frame, config.octree.depth_min, config.octree.depth_max)


def score(rendered: Rendering, truth: Frame, lpips: Lpips | None = None) -> dict:
    """PSNR, SSIM, MS-SSIM, depth L1 and, with an available ``lpips``, LPIPS (None otherwise); and
    ``psnr_affine``, the PSNR once the frame's own two-parameter affine colour map is fitted to the render
    (``metrics.psnr_affine``): ``psnr`` is the render as it is, raw."""
    from ogmapping.quality.metrics import depth_l1_cm, ms_ssim, psnr, psnr_affine, ssim

    return {
        "psnr": psnr(rendered.color, truth.rgb),
        "psnr_affine": psnr_affine(rendered.color, truth.rgb),
        "ssim": ssim(rendered.color, truth.rgb),
        "ms_ssim": ms_ssim(rendered.color, truth.rgb),
        "depth_l1_cm": depth_l1_cm(rendered.depth, truth.depth),
        "lpips": lpips(rendered.color, truth.rgb) if lpips is not None else None,
    }


def side_by_side(rendered: Rendering, truth: Frame) -> np.ndarray:
    """Render | ground truth on top, rendered depth | measured depth below, as a BGR uint8 image."""
    top = np.concatenate([rendered.color, truth.rgb], axis=1)
    far = max(float(np.percentile(truth.depth[truth.depth > 0], 99)) if (truth.depth > 0).any() else 1.0, 1e-3)
    depths = np.concatenate([rendered.depth, truth.depth], axis=1) / far
    bottom = cv2.applyColorMap((np.clip(depths, 0, 1) * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    top_bgr = cv2.cvtColor((np.clip(top, 0, 1) * 255).astype(np.uint8), cv2.COLOR_RGB2BGR)
    return np.concatenate([top_bgr, bottom], axis=0)


def spread(items: list[int], count: int) -> list[int]:
    """Up to ``count`` items evenly spaced over the list, first and last included."""
    if len(items) <= count:
        return list(items)
    return [items[round(i * (len(items) - 1) / (count - 1))] for i in range(count)]


@dataclass
class Evaluation:
    """Per-split summaries (``streamed``, ``heldout``), render timing and what LPIPS was."""

    splits: dict[str, dict[str, Any]]
    renders: int
    render_seconds: float
    lpips: str  # the network, or why it did not run (``Lpips.description``)

    @property
    def render_fps(self) -> float | None:
        return self.renders / self.render_seconds if self.render_seconds > 0 else None


class LocalMap(Protocol):
    """What ``mapper_render`` needs of a ``Mapper``."""

    def render(self, c2w: np.ndarray, intrinsics: Intrinsics, keyframe: int | None = None) -> Rendering: ...

    def nearest_keyframe(self, frame_index: int) -> int | None: ...


def mapper_render(mapper: LocalMap) -> Render:
    """Render through a local mapper at a pose of the judged frame's time: moved as the keyframe nearest that
    frame was moved by refinement (``Mapper.render``; the pose itself without ``poses.refine``), since the
    pose is the client's and the map follows its refined poses."""
    return lambda c2w, camera, frame: mapper.render(c2w, camera, mapper.nearest_keyframe(frame.index))


def own_pose(frame: Frame) -> np.ndarray:
    """Judge a view at the pose the mapper was given with it."""
    return frame.c2w


def evaluate_views(
    frames: FrameSet, config: MapperConfig, render: Render, out: Path | None = None, progress: bool = True,
    device: str | torch.device = "cpu", pose: Pose = own_pose, prefix: str = "",
) -> Evaluation:
    """Render every streamed and held-out view at ``pose(frame)`` and score it against the frame; with
    ``out``, write previews of ``spread`` positions.

    ``device`` is where LPIPS runs; previews are ``out/{prefix}{split}_{position:06d}.png``.
    """
    from ogmapping.quality.metrics import Lpips, summarise

    selection = frames.selection
    previews = set(spread(selection.streamed, PREVIEW_COUNT)) | set(spread(selection.heldout, PREVIEW_COUNT))
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
    lpips = Lpips(device)
    splits = {}
    render_seconds, renders = 0.0, 0
    for split, positions in (("streamed", selection.streamed), ("heldout", selection.heldout)):
        per_frame = []
        desc = f"evaluating {prefix}{split}"
        for position in tqdm(positions, desc=desc, unit="frame", disable=not progress):
            truth = ground_truth(frames.load(position), config)
            at = pose(truth)
            tic = time.perf_counter()
            rendered = render(at, truth.color_intrinsics, truth)
            render_seconds += time.perf_counter() - tic
            renders += 1
            per_frame.append(score(rendered, truth, lpips))
            if out is not None and position in previews:
                cv2.imwrite(str(out / f"{prefix}{split}_{position:06d}.png"), side_by_side(rendered, truth))
        splits[split] = summarise(per_frame)
    return Evaluation(splits, renders, render_seconds, lpips.description)
