"""Renders at a client pose of a frame's time: the pose moves as refinement moved the keyframe nearest that frame
(refined x client^-1), is unchanged without refinement, and a map loaded from a snapshot answers the same."""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
import torch

from ogmapping.cli import main as ogmap
from ogmapping.config import resolve
from ogmapping.mapper import Mapper
from ogmapping.quality.evaluation import mapper_render, open_frames
from ogmapping.queries import KeyframePose, in_map_frame, nearest

TINY = {"keyframes.first_iterations": "6", "keyframes.iterations": "2", "keyframes.overlap_threshold": "0.95"}
# A correction set by hand on every refined keyframe: a few centimetres and a degree, so renders differ.
MOVES = (torch.tensor([0.03, -0.02, 0.01, 0.0, 0.02, 0.0], dtype=torch.float64),
         torch.tensor([-0.02, 0.01, 0.03, 0.015, 0.0, -0.01], dtype=torch.float64))


def _frames():
    frames = open_frames("synthetic", "synthetic", "0:8", 1, 0.25, n_frames=40)
    return [frames.load(position) for position in range(8)]


def _mapped(refine: bool) -> Mapper:
    mapper = Mapper(resolve("sparse-fast", overrides={**TINY, "poses.refine": str(refine).lower()}))
    for frame in _frames():
        mapper.process(frame)
    return mapper


@pytest.fixture(scope="module")
def refined() -> Mapper:
    mapper = _mapped(True)
    corrected = [keyframe for keyframe in mapper.keyframes.keyframes if keyframe.correction is not None]
    assert len(mapper.keyframes) >= 3 and len(corrected) == len(mapper.keyframes) - 1
    with torch.no_grad():
        for number, keyframe in enumerate(corrected):
            keyframe.correction.delta.copy_(MOVES[number % 2].to(keyframe.correction.delta.dtype))
    return mapper


def test_the_nearest_keyframe_is_by_frame_index_the_earlier_on_a_tie():
    assert nearest([], 5) is None
    assert [nearest([0, 4, 10], index) for index in (0, 1, 2, 3, 7, 8, 100)] == [0, 0, 0, 1, 1, 2, 2]


def test_a_pose_moves_as_its_keyframe_did():
    client = np.eye(4)
    client[:3, 3] = (1.0, 2.0, 3.0)
    refined = client.copy()
    refined[:3, 3] += (0.1, 0.0, 0.0)
    keyframe = KeyframePose(4, client, refined, False)
    assert np.allclose(in_map_frame(keyframe, client), refined)
    near = client.copy()
    near[:3, 3] += (0.0, 0.5, 0.0)
    assert np.allclose(in_map_frame(keyframe, near)[:3, 3], near[:3, 3] + (0.1, 0.0, 0.0))
    assert np.array_equal(in_map_frame(KeyframePose(4, client, client, False), near), near)


def test_a_render_at_a_frame_time_is_the_render_at_the_moved_pose(refined: Mapper):
    poses = refined.keyframe_poses()
    frame = _frames()[5]
    position = refined.nearest_keyframe(frame.index)
    assert position == nearest([pose.index for pose in poses], frame.index)
    chosen = poses[position]
    assert not np.allclose(chosen.refined_c2w, chosen.client_c2w)
    moved = chosen.refined_c2w @ np.linalg.inv(chosen.client_c2w) @ frame.c2w
    at_time = refined.render(frame.c2w, frame.color_intrinsics, position)
    assert np.array_equal(at_time.color, refined.render(moved, frame.color_intrinsics).color)
    assert not np.array_equal(at_time.color, refined.render(frame.c2w, frame.color_intrinsics).color)
    through = mapper_render(refined)(frame.c2w, frame.color_intrinsics, frame)
    assert np.array_equal(through.color, at_time.color)
    with pytest.raises(ValueError, match="keyframe 99: the map has"):
        refined.render(frame.c2w, frame.color_intrinsics, 99)


def test_without_refinement_a_frame_time_changes_nothing():
    mapper = _mapped(False)
    frame = _frames()[5]
    position = mapper.nearest_keyframe(frame.index)
    assert position is not None
    assert np.array_equal(mapper.render(frame.c2w, frame.color_intrinsics, position).color,
                          mapper.render(frame.c2w, frame.color_intrinsics).color)
    assert Mapper(mapper.config).nearest_keyframe(frame.index) is None  # no keyframes yet


def test_a_map_loaded_from_a_snapshot_moves_poses_as_its_maker_did(refined: Mapper):
    restored = Mapper.restore(refined.snapshot())
    assert len(restored.keyframes) == 0
    recorded, live = restored.keyframe_poses(), refined.keyframe_poses()
    assert [pose.index for pose in recorded] == [pose.index for pose in live]
    assert all(np.allclose(a.refined_c2w, b.refined_c2w, atol=1e-6) for a, b in zip(recorded, live, strict=True))
    frame = _frames()[6]
    position = restored.nearest_keyframe(frame.index)
    assert position == refined.nearest_keyframe(frame.index)
    moved = in_map_frame(recorded[position], frame.c2w)
    assert np.allclose(moved, in_map_frame(live[position], frame.c2w), atol=1e-5)
    assert np.array_equal(restored.render(frame.c2w, frame.color_intrinsics, position).color,
                          restored.render(moved, frame.color_intrinsics).color)
    # Once it maps a keyframe of its own, positions name its own keyframes.
    restored.process(dataclasses.replace(frame, index=100))
    assert [pose.index for pose in restored.keyframe_poses()] == [100]
    assert restored.nearest_keyframe(frame.index) == 0


def test_a_snapshot_whose_recorded_poses_disagree_is_refused(refined: Mapper):
    state = refined.state()
    state.tensors["poses.client_c2w"] = state.tensors["poses.client_c2w"][:-1]
    with pytest.raises(ValueError, match=r"poses.client_c2w .* must match poses.refined_c2w"):
        Mapper.from_state(state)
    del state.tensors["poses.client_c2w"]  # a snapshot written before the client poses were kept: none recorded
    assert Mapper.from_state(state).keyframe_poses() == []


def test_ogmap_render_moves_a_pose_of_a_named_frame(refined: Mapper, tmp_path):
    snapshot = tmp_path / "map.safetensors"
    snapshot.write_bytes(refined.snapshot())
    frame = _frames()[5]
    camera = frame.color_intrinsics
    np.savetxt(tmp_path / "pose.txt", frame.c2w)
    common = ["render", "--snapshot", str(snapshot), "--pose", str(tmp_path / "pose.txt"),
              "--intrinsics", f"{camera.fx},{camera.fy},{camera.cx},{camera.cy}", "--size",
              f"{camera.width}x{camera.height}"]
    assert ogmap([*common, "--frame", str(frame.index), "--out", str(tmp_path / "at_frame")]) == 0
    assert ogmap([*common, "--out", str(tmp_path / "in_map")]) == 0
    restored = Mapper.restore(snapshot.read_bytes())
    expected = restored.render(frame.c2w, camera, restored.nearest_keyframe(frame.index)).color
    written = cv2.cvtColor(cv2.imread(str(tmp_path / "at_frame" / "color.png")), cv2.COLOR_BGR2RGB)
    assert np.array_equal(written, (expected * 255).round().astype(np.uint8))
    assert (tmp_path / "at_frame" / "color.png").read_bytes() != (tmp_path / "in_map" / "color.png").read_bytes()
