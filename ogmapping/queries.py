"""What a map answers: renders from any pose, every anchor's Gaussians, statistics, the keyframes' poses.

Each takes the map model (and the keyframes where it needs them) with the mapper's lock held and on
its stream (``Mapper`` wraps them); renders and decodes read the map's moving average.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ogmapping.frames.camera import Intrinsics
from ogmapping.mapping.model import MapModel
from ogmapping.model.gaussians import GaussianSet
from ogmapping.optim.keyframes import Keyframe, KeyframeSet
from ogmapping.stats import MapStats, PoseSummary


@dataclass
class Rendered:
    color: np.ndarray  # (H, W, 3) float32 in [0, 1]
    depth: np.ndarray  # (H, W) float32 metres, 0 where nothing was rendered
    alpha: np.ndarray  # (H, W) float32


@dataclass(frozen=True)
class KeyframePose:
    """A keyframe's pose as the client gave it and as refinement left it (the same without refinement)."""

    index: int
    client_c2w: np.ndarray  # (4, 4)
    refined_c2w: np.ndarray  # (4, 4)
    clamped: bool


def nearest(indices: list[int], frame_index: int) -> int | None:
    """The position in ``indices`` (keyframes' frame indices) nearest ``frame_index`` (the earlier on a tie),
    None for none."""
    if not indices:
        return None
    return min(range(len(indices)), key=lambda position: (abs(indices[position] - frame_index), position))


def in_map_frame(keyframe: KeyframePose, c2w: np.ndarray) -> np.ndarray:
    """A client pose from around ``keyframe``'s time, moved as refinement moved that keyframe (refined x
    client^-1): the client's poses drift, and the map follows its refined ones, so a pose the client gave
    near a keyframe is off the map as far as that keyframe's was. Unchanged (bit for bit) without refinement."""
    c2w = np.asarray(c2w, dtype=np.float64)
    if np.array_equal(keyframe.refined_c2w, keyframe.client_c2w):
        return c2w
    return keyframe.refined_c2w @ np.linalg.inv(keyframe.client_c2w) @ c2w


def render(model: MapModel, c2w: np.ndarray, intrinsics: Intrinsics) -> Rendered:
    """Colour, depth and alpha from any pose (camera-to-world) and intrinsics."""
    pose = torch.as_tensor(np.asarray(c2w), dtype=model.profile.precision, device=model.device)
    with torch.no_grad(), model.average.applied():
        _, output = model.render(pose, intrinsics)
    return Rendered(
        color=output.color.clamp(0, 1).cpu().numpy().astype(np.float32),
        depth=output.depth.cpu().numpy().astype(np.float32),
        alpha=output.alpha.cpu().numpy().astype(np.float32),
    )


def decode_all(model: MapModel, camera_center: np.ndarray, max_anchors: int = 0) -> GaussianSet:
    """Every anchor's Gaussians as seen from ``camera_center`` (colours and opacities depend on the
    viewpoint through the decoders); no frustum culling, no gradients. ``max_anchors`` > 0 decodes
    only that many, evenly spread over the map, so a preview costs a bounded time."""
    center = torch.as_tensor(np.asarray(camera_center), dtype=torch.float32, device=model.device)
    with torch.no_grad(), model.average.applied():
        count = len(model.anchors)
        stride = -(-count // max_anchors) if max_anchors and count > max_anchors else 1
        return model.decode(center, torch.arange(0, count, stride, device=model.device))


def keyframe_pose(keyframe: Keyframe) -> KeyframePose:
    """A keyframe's pose as the client gave it and as refinement has left it so far."""
    client = keyframe.c2w.detach().double().cpu().numpy()
    report = keyframe.correction.report(keyframe.c2w) if keyframe.correction is not None else None
    return KeyframePose(keyframe.index, client, client if report is None else report.refined_c2w,
                        report is not None and report.clamped)


def keyframe_poses(keyframes: KeyframeSet) -> list[KeyframePose]:
    """Every keyframe's pose as the client gave it and as refinement has left it so far."""
    return [keyframe_pose(keyframe) for keyframe in keyframes.keyframes]


def pose_summary(keyframes: KeyframeSet) -> PoseSummary:
    """Pose refinement over the keyframes' corrections."""
    reports = [keyframe.correction.report(keyframe.c2w) for keyframe in keyframes.keyframes
               if keyframe.correction is not None]
    metres = [report.translation_m for report in reports] or [0.0]
    degrees = [report.rotation_deg for report in reports] or [0.0]
    return PoseSummary(len(reports), float(np.mean(metres)), max(metres), float(np.mean(degrees)), max(degrees),
                       sum(report.clamped for report in reports))


def map_stats(model: MapModel, keyframes: KeyframeSet) -> MapStats:
    """Map statistics as one consistent record."""
    return MapStats(
        frames=model.frames,
        keyframes=len(keyframes),
        iterations=model.iterations,
        anchors=len(model.anchors),
        anchors_per_level=tuple(model.anchors.level_counts(model.config.octree.max_level)),
        gaussians=model.last_gaussians,
        octree_cells_per_level=tuple(model.octree.count(level) for level in range(model.octree.levels)),
        device=str(model.device),
        backend=model.backend,
        timings=model.timer.totals(),
        poses=pose_summary(keyframes) if model.config.poses.refine else None,
        config=model.config.to_dict(),
    )


def camera_centroid(model: MapModel) -> np.ndarray | None:
    """Mean camera position of every frame mapped into this map (across snapshots), or None for a map
    that has none on record (an empty one, or a snapshot written before it was kept)."""
    if not model.camera_positions:
        return None
    return (model.camera_position_sum / model.camera_positions).numpy()


def anchor_centroid(model: MapModel) -> np.ndarray:
    """Mean anchor centre (the origin for an empty map)."""
    if not len(model.anchors):
        return np.zeros(3)
    return model.anchors.positions.mean(0).double().cpu().numpy()
