"""Pose refinement: the correction's algebra, its optimiser and bound, and the mapper carrying it."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from ogmapping.config import PosesConfig, resolve
from ogmapping.frames.rotation import axis_angle_matrix
from ogmapping.mapper import Mapper
from ogmapping.optim.poses import STATE_SIZE, TRACK_CHECK_STEPS, PoseCorrection, settled
from ogmapping.persist import map_io, snapshot
from ogmapping.quality.evaluation import open_frames
from ogmapping.runtime.time_budget import Budget

TINY = {"keyframes.first_iterations": "6", "keyframes.iterations": "2"}


def _rodrigues(axis_angle: np.ndarray) -> np.ndarray:
    angle = float(np.linalg.norm(axis_angle))
    return axis_angle_matrix(axis_angle / angle, angle)


def _client_pose() -> torch.Tensor:
    c2w = torch.eye(4, dtype=torch.float64)
    c2w[:3, :3] = torch.from_numpy(_rodrigues(np.array([0.3, -0.2, 0.5])))
    c2w[:3, 3] = torch.tensor([1.0, -2.0, 0.5])
    return c2w


def test_zero_correction_is_the_client_pose_and_a_correction_moves_centre_and_axes():
    c2w = _client_pose()
    correction = PoseCorrection("cpu", torch.float64)
    assert torch.equal(correction.refined(c2w), c2w)
    with torch.no_grad():
        correction.delta.copy_(torch.tensor([0.01, 0.0, -0.02, 0.0, 0.0, 0.1], dtype=torch.float64))
    refined = correction.refined(c2w)
    assert torch.allclose(refined[:3, 3], c2w[:3, 3] + torch.tensor([0.01, 0.0, -0.02], dtype=torch.float64))
    expected = torch.from_numpy(_rodrigues(np.array([0.0, 0.0, 0.1]))) @ c2w[:3, :3]
    assert torch.allclose(refined[:3, :3], expected, atol=1e-12)
    assert torch.equal(refined[3], c2w[3])
    report = correction.report(c2w)
    assert report.translation_m == pytest.approx(math.hypot(0.01, 0.02))
    assert report.rotation_deg == pytest.approx(math.degrees(0.1))


def test_a_step_follows_the_gradient_at_the_learning_rates():
    settings = PosesConfig(translation_lr=0.002, rotation_lr=0.001)
    correction = PoseCorrection("cpu")
    correction.step(settings)  # no gradient yet: nothing happens
    assert correction.steps == 0
    correction.delta.grad = torch.tensor([1.0, -3.0, 0.0, 0.5, 0.0, -2.0])
    correction.step(settings)
    # Gradient descent: a small gradient (a pose near its optimum) makes a small step.
    assert torch.allclose(correction.delta.detach(), torch.tensor([-0.002, 0.006, 0.0, -0.0005, 0.0, 0.002]))
    assert correction.delta.grad is None and correction.steps == 1 and not correction.clamped


def test_the_prior_costs_its_weight_at_the_bound():
    settings = PosesConfig(prior=0.3, max_translation=0.05, max_rotation=2.0)
    correction = PoseCorrection("cpu", torch.float64)
    with torch.no_grad():
        correction.delta[0] = 0.05
    assert float(correction.prior(settings).detach()) == pytest.approx(0.3)
    with torch.no_grad():
        correction.delta.zero_()
        correction.delta[4] = math.radians(2.0)
    assert float(correction.prior(settings).detach()) == pytest.approx(0.3)


def test_a_runaway_correction_is_clamped_to_the_bound_and_reported():
    settings = PosesConfig(translation_lr=1.0, rotation_lr=1.0, max_translation=0.1, max_rotation=5.0)
    correction = PoseCorrection("cpu", torch.float64)
    correction.delta.grad = torch.tensor([-1.0, 0.0, 0.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    correction.step(settings)
    assert float(correction.translation.detach().norm()) == pytest.approx(0.1)
    assert correction.clamped
    correction.delta.grad = torch.tensor([0.0, 0.0, 0.0, 1.0, 1.0, 0.0], dtype=torch.float64)
    correction.step(settings)
    assert float(correction.rotation.detach().norm()) == pytest.approx(math.radians(5.0))
    assert correction.report(_client_pose()).clamped


def test_state_round_trip_and_bad_rows():
    correction = PoseCorrection("cpu")
    correction.delta.grad = torch.arange(6, dtype=torch.float32) - 2.5
    correction.step(PosesConfig())
    row = correction.state()
    assert row.shape == (STATE_SIZE,)
    again = PoseCorrection.from_state(row, "cpu", torch.float32)
    assert torch.equal(again.delta.detach(), correction.delta.detach()) and again.delta.requires_grad
    assert again.steps == 1 and again.clamped == correction.clamped
    correction.hold()
    held = PoseCorrection.from_state(correction.state(), "cpu", torch.float32)
    assert held.held and not held.delta.detach().any()
    older = PoseCorrection.from_state(row[:-1], "cpu", torch.float32)  # written before ``held`` was kept
    assert torch.equal(older.delta.detach(), again.delta.detach()) and not older.held
    with pytest.raises(ValueError, match="pose correction"):
        PoseCorrection.from_state(row[:-2], "cpu", torch.float32)
    with pytest.raises(ValueError, match="pose correction"):
        PoseCorrection.from_state(torch.full((STATE_SIZE,), math.nan, dtype=torch.float64), "cpu", torch.float32)


def _frames(count: int):
    frames = open_frames("synthetic", "synthetic", f"0:{count}", 1, 0.25, n_frames=40)
    return [frames.load(position) for position in range(count)]


def test_without_refinement_the_frame_reports_the_client_pose_and_snapshots_hold_the_keyframes_path():
    mapper = Mapper(resolve("sparse-fast", overrides=TINY))
    frames = _frames(2)
    for frame in frames:
        result = mapper.process(frame)
        assert np.array_equal(result.pose.refined_c2w, frame.c2w) and not result.pose.clamped
    assert mapper.stats().poses is None and "poses" not in mapper.stats().to_dict()
    path = map_io.keyframe_path(snapshot.decode(mapper.snapshot()))
    assert np.array_equal(path, np.array([pose.refined_c2w for pose in mapper.keyframe_poses()]))
    assert np.allclose(path[0], frames[0].c2w, atol=1e-6)  # kept in float32


def test_a_keyframe_path_that_is_not_finite_4x4_poses_is_refused():
    state = Mapper(resolve("sparse-fast", overrides=TINY)).state()
    assert map_io.keyframe_path(state).shape == (0, 4, 4)
    state.tensors.pop("poses.refined_c2w")
    assert map_io.keyframe_path(state).shape == (0, 4, 4)  # a snapshot written before paths were kept
    for bad in (torch.zeros(2, 3, 4), torch.full((1, 4, 4), float("nan"))):
        state.tensors["poses.refined_c2w"] = bad
        with pytest.raises(ValueError, match=r"poses\.refined_c2w must hold finite 4x4 poses"):
            map_io.keyframe_path(state)


def test_refinement_keeps_the_first_keyframe_and_its_poses_survive_checkpoints_and_snapshots():
    config = resolve("sparse-fast", overrides={**TINY, "poses.refine": "true", "poses.track_min_gain": "0",
                                               "keyframes.overlap_threshold": "0.99"})
    mapper = Mapper(config)
    frames = _frames(4)
    results = [mapper.process(frame) for frame in frames]
    assert np.array_equal(results[0].pose.refined_c2w, frames[0].c2w)
    assert mapper.keyframes.keyframes[0].correction is None
    later = mapper.keyframes.keyframes[1:]
    assert later and all(keyframe.correction is not None for keyframe in later)
    poses = mapper.keyframe_poses()
    tensors = snapshot.decode(mapper.snapshot()).tensors
    assert tensors["poses.keyframe_indices"].tolist() == [pose.index for pose in poses]
    assert np.allclose(tensors["poses.refined_c2w"].numpy(), np.array([pose.refined_c2w for pose in poses]))
    assert np.array_equal(tensors["poses.client_c2w"][0].numpy(), poses[0].client_c2w)
    resumed = Mapper.from_state(snapshot.decode(snapshot.encode(mapper.state(training_state=True), half=False)),
                                training_state=True)
    for kept, original in zip(resumed.keyframes.keyframes, mapper.keyframes.keyframes, strict=True):
        if original.correction is None:
            assert kept.correction is None
        else:
            assert torch.equal(kept.correction.state(), original.correction.state())
    summary = mapper.stats().poses
    assert summary.refined_keyframes == len(mapper.keyframes) - 1
    assert summary.max_correction_m >= summary.mean_correction_m > 0.0


def _pixel_shift(frame, truth: np.ndarray, pose: np.ndarray) -> float:
    """Mean image distance (pixels) between the frame's depth points seen from ``truth`` and from ``pose``:
    a pose error as the images see it (a small rotation and a small translation can explain each other)."""
    k = frame.color_intrinsics
    v, u = np.nonzero(frame.depth > 0)
    z = frame.depth[v, u]
    points = truth @ np.stack([(u + 0.5 - k.cx) / k.fx * z, (v + 0.5 - k.cy) / k.fy * z, z, np.ones_like(z)])
    x, y, depth, _ = np.linalg.inv(pose) @ points
    return float(np.hypot(x / depth * k.fx + k.cx - 0.5 - u, y / depth * k.fy + k.cy - 0.5 - v).mean())


def test_refinement_moves_a_displaced_pose_towards_the_truth():
    # The streamed view's own mapping steps, at the tracking rates, move its pose (``sparse`` moves only its
    # keyframes', at a quarter of them).
    frames = open_frames("synthetic", "synthetic", "0:7", 1, 1.0, n_frames=40)  # 320x240
    loaded = [frames.load(position) for position in range(7)]
    mapper = Mapper(resolve("sparse", overrides={"poses.refine": "true", "poses.track_iterations": "0",
                                                 "poses.view_steps": "true", "poses.mapping_rate": "1"}))
    for frame in loaded[:6]:
        mapper.process(frame)
    displaced = loaded[6]
    truth = displaced.c2w.copy()
    displaced.c2w = truth.copy()
    displaced.c2w[:3, 3] += np.array([0.012, -0.008, 0.0])
    result = mapper.process(displaced)
    before = _pixel_shift(displaced, truth, displaced.c2w)
    assert before > 1.5
    assert _pixel_shift(displaced, truth, result.pose.refined_c2w) < 0.6 * before and not result.pose.clamped


def test_a_held_correction_stays_at_the_client_pose():
    correction = PoseCorrection("cpu")
    correction.delta.grad = torch.ones(6)
    correction.step(PosesConfig())
    correction.hold()
    correction.delta.grad = torch.ones(6)
    correction.step(PosesConfig())
    assert correction.held and not correction.delta.detach().any() and correction.steps == 1


def test_a_pose_has_settled_when_the_second_step_gains_little():
    losses = [torch.tensor(value) for value in (1.0, 0.9, 0.89)]
    assert settled(losses, 0.02) and not settled(losses, 0.005)
    assert not settled([torch.tensor(value) for value in (1.0, 0.9, 0.8)], 0.02)
    assert not settled([torch.tensor(value) for value in (1.0, 0.9, 1.2)], 0.0)  # 0: every pose moves


@pytest.mark.parametrize(("track_iterations", "fine_iterations", "newton_iterations"),
                         [(2, 0, 0), (5, 0, 0), (5, 3, 0), (2, 0, 3)])
def test_tracking_that_settles_holds_every_pose_and_maps_as_without_refinement(track_iterations, fine_iterations,
                                                                               newton_iterations):
    frames = _frames(4)
    overrides = {**TINY, "keyframes.overlap_threshold": "0.99"}
    plain = Mapper(resolve("sparse-fast", overrides=overrides))
    gated = Mapper(resolve("sparse-fast", overrides={**overrides, "poses.refine": "true", "poses.track_min_gain": "1",
                                                     "poses.track_iterations": str(track_iterations),
                                                     "poses.track_fine_iterations": str(fine_iterations),
                                                     "poses.track_newton_iterations": str(newton_iterations)}))
    for frame in frames:
        result = gated.process(frame)
        plain.process(frame)
        assert np.allclose(result.pose.refined_c2w, frame.c2w, rtol=0, atol=1e-6)
    corrections = [keyframe.correction for keyframe in gated.keyframes.keyframes[1:]]
    assert corrections and all(correction.held for correction in corrections)
    assert all(correction.steps == TRACK_CHECK_STEPS for correction in corrections)  # tracking stopped there
    held = gated.state().tensors
    for name, tensor in plain.state().tensors.items():
        assert torch.equal(tensor, held[name]), name


def test_tracking_only_keyframes_gates_their_corrections_and_leaves_other_frames_as_given():
    frames = _frames(6)
    overrides = {**TINY, "poses.refine": "true", "poses.tracked": "keyframes", "poses.view_steps": "false",
                 "poses.track_newton_iterations": "0"}
    plain = Mapper(resolve("sparse-fast", overrides=TINY))
    gated = Mapper(resolve("sparse-fast", overrides={**overrides, "poses.track_min_gain": "1"}))
    results = []
    for frame in frames:
        results.append(gated.process(frame))
        plain.process(frame)
    assert any(not result.keyframe for result in results) and sum(result.keyframe for result in results) > 1
    corrections = [keyframe.correction for keyframe in gated.keyframes.keyframes[1:]]
    assert all(correction.held and correction.steps == TRACK_CHECK_STEPS for correction in corrections)
    # Every pose stays as given: the map is the one made without refinement, to the bit.
    held = gated.state().tensors
    for name, tensor in plain.state().tensors.items():
        assert torch.equal(tensor, held[name]), name

    moving = Mapper(resolve("sparse-fast", overrides={**overrides, "poses.track_min_gain": "0"}))
    for frame, result in zip(frames, results, strict=True):
        tracked = moving.process(frame)
        assert tracked.keyframe == result.keyframe
        if not tracked.keyframe:  # a streamed frame is neither tracked nor moved by its own steps
            assert not tracked.pose.translation.any() and not tracked.pose.rotation.any()
    assert all(keyframe.correction.steps >= 2 for keyframe in moving.keyframes.keyframes[1:])


def test_a_keyframe_is_tracked_against_the_map_without_its_own_anchors():
    loaded = _frames(3)
    displaced = loaded[2]
    displaced.c2w = displaced.c2w.copy()
    displaced.c2w[:3, 3] += np.array([0.01, -0.01, 0.0])
    mapper = Mapper(resolve("sparse-fast", overrides={
        **TINY, "keyframes.first_iterations": "40", "keyframes.overlap_threshold": "0.99",  # every frame a keyframe
        "poses.refine": "true", "poses.tracked": "keyframes", "poses.view_steps": "false",
        "poses.track_min_gain": "0"}))
    for frame in loaded[:2]:
        mapper.process(frame)
    anchors = len(mapper.model.anchors)
    rendered, in_map = [], []  # the rows tracking decoded, and the map's size while it tracked
    decode, track = mapper.model.decode, mapper.tracker.track

    def tracking(*args, **kwargs):
        in_map.append(len(mapper.model.anchors))
        mapper.model.decode = lambda center, rows: rendered.append(rows) or decode(center, rows)
        track(*args, **kwargs)
        mapper.model.decode = decode

    mapper.tracker.track = tracking
    result = mapper.process(displaced)
    assert result.keyframe and in_map[0] > anchors  # tracked once it had added anchors of its own...
    assert len(rendered) == 1 and 0 < int(rendered[0].max()) < anchors  # ...which it did not render
    correction = mapper.keyframes.keyframes[-1].correction
    assert correction.steps >= TRACK_CHECK_STEPS and result.pose.translation_m > 0  # tracking moved it


@pytest.mark.parametrize("key", ["poses.track_fine_iterations", "poses.track_newton_iterations"])
def test_further_tracking_steps_move_a_pose_that_tracking_moves(key):
    loaded = _frames(3)
    displaced = loaded[2]
    displaced.c2w = displaced.c2w.copy()
    displaced.c2w[:3, 3] += np.array([0.01, -0.01, 0.0])
    refined = {}
    for further in ("0", "3"):
        mapper = Mapper(resolve("sparse-fast", overrides={
            **TINY, "keyframes.first_iterations": "40",  # a map that covers pixels fully, which tracking counts
            "poses.refine": "true", "poses.track_min_gain": "0", "poses.track_iterations": "2",
            key: further, "poses.view_steps": "false"}))
        for frame in loaded[:2]:
            mapper.process(frame)
        refined[further] = mapper.process(displaced).pose.refined_c2w
    assert not np.allclose(refined["0"], refined["3"], rtol=0, atol=1e-7)
    assert not np.allclose(refined["0"], displaced.c2w, rtol=0, atol=1e-7)  # tracking itself moved it


def _mapped_with_exact_poses(review: str = "true") -> tuple[Mapper, list]:
    frames = open_frames("synthetic", "synthetic", "0:4", 1, 0.5, n_frames=40)  # 160x120
    loaded = [frames.load(position) for position in range(4)]
    mapper = Mapper(resolve("sparse-fast", overrides={
        **TINY, "keyframes.first_iterations": "60", "keyframes.overlap_threshold": "0.99",  # every frame a keyframe
        "poses.refine": "true", "poses.track_iterations": "0", "poses.view_steps": "false", "poses.review": review}))
    for frame in loaded:
        mapper.process(frame)
    return mapper, loaded


def _review(mapper: Mapper, frame, client_c2w: np.ndarray, delta: list[float]) -> torch.Tensor:
    """The correction ``delta`` of ``frame`` seen from ``client_c2w``, after its review."""
    model = mapper.model
    prepared = mapper.prepare(dataclasses.replace(frame, c2w=client_c2w))
    rgb, depth, c2w = model.upload(prepared.rgb, prepared.depth, prepared.c2w)
    correction = PoseCorrection(model.device)
    with torch.no_grad():
        correction.delta.copy_(torch.tensor(delta))
    mapper.tracker.review(frame.color_intrinsics, (rgb, depth, c2w), correction)
    return correction.delta.detach()


def test_a_review_puts_back_a_correction_the_client_pose_fits_better_and_keeps_one_that_fits_better():
    mapper, loaded = _mapped_with_exact_poses()
    frame = loaded[2]
    off = [0.015, -0.01, 0.0, 0.0, 0.01, 0.0]
    assert not _review(mapper, frame, frame.c2w, off).any()  # the client's exact pose renders the frame closer
    displaced = frame.c2w.copy()
    displaced[:3, 3] -= np.array([0.015, -0.01, 0.0])
    kept = _review(mapper, frame, displaced, [0.015, -0.01, 0.0, 0.0, 0.0, 0.0])  # the correction undoes the error
    assert torch.equal(kept, torch.tensor([0.015, -0.01, 0.0, 0.0, 0.0, 0.0]))


@pytest.mark.parametrize("stride", [2, 4])
def test_a_review_with_newton_steps_retracks_a_correction_towards_the_pose_the_map_fits(stride):
    mapper, loaded = _mapped_with_exact_poses()
    frame = loaded[2]
    displaced = frame.c2w.copy()
    displaced[:3, 3] -= np.array([0.015, -0.01, 0.0])
    truth = torch.tensor([0.015, -0.01, 0.0, 0.0, 0.0, 0.0])
    assert not _review(mapper, frame, displaced, [0.0] * 6).any()  # reviewed alone, a zero correction stays zero
    mapper.config.poses.review_newton_iterations = 2
    mapper.config.poses.review_newton_stride = stride
    widths = []  # of every render the review makes
    make_camera = mapper.model.camera
    mapper.model.camera = lambda c2w, intrinsics, blur: widths.append(intrinsics.width) or make_camera(
        c2w, intrinsics, blur)
    retracked = _review(mapper, frame, displaced, [0.0] * 6)
    assert (retracked - truth)[:3].norm() < 0.5 * truth[:3].norm(), retracked  # more than half the way back
    # The test at the tracking stride (two renders), the steps' renders at theirs.
    assert widths[:2] == [80, 80] and set(widths[2:]) == {160 // stride}, widths


@pytest.mark.parametrize("review", ["true", "false"])
def test_after_each_frame_one_keyframe_correction_in_turn_is_reviewed(review):
    mapper, loaded = _mapped_with_exact_poses(review)
    corrections = [keyframe.correction for keyframe in mapper.keyframes.keyframes[1:]]
    assert len(corrections) == 3
    with torch.no_grad():
        for correction in corrections:
            correction.delta.copy_(torch.tensor([0.015, -0.01, 0.0, 0.0, 0.01, 0.0]))
    turn = mapper.model.frames % len(corrections)  # the correction the next frame's review takes
    mapper.process(loaded[3])
    if review == "false":
        assert all(correction.delta.any() for correction in corrections)
        return
    # The reviewed one is back at its client's (exact) pose; the others moved only by their window steps.
    assert [not correction.delta.any() for correction in corrections] == [i == turn for i in range(3)]


def test_a_frame_out_of_time_leaves_the_review_to_the_next():
    mapper, loaded = _mapped_with_exact_poses()
    corrections = [keyframe.correction for keyframe in mapper.keyframes.keyframes[1:]]
    with torch.no_grad():
        for correction in corrections:
            correction.delta.copy_(torch.tensor([0.015, -0.01, 0.0, 0.0, 0.01, 0.0]))
    mapper.process(loaded[3], Budget(seconds=0.0))  # no step either: every correction stays where it was
    assert all(correction.delta.any() for correction in corrections)

