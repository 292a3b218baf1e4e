"""TUM trajectory files and seeded pose noise (``ogmapping.frames.trajectory``)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from ogmapping.datasets.synthetic import trajectory as synthetic_trajectory
from ogmapping.frames.camera import validate_pose
from ogmapping.frames.frame import Frame
from ogmapping.frames.rotation import axis_angle_matrix
from ogmapping.frames.trajectory import (
    Trajectory,
    frame_key,
    perturb,
    pose_errors,
    read_tum,
    write_tum,
)
from ogmapping.quality.evaluation import open_frames

POSES = synthetic_trajectory(12)
KEYS = [i / 30.0 for i in range(12)]


def frame(index: int, timestamp: float | None) -> Frame:
    empty = np.zeros((1, 1), dtype=np.float32)
    return Frame(index, empty, empty, None, None, np.eye(4), timestamp)  # type: ignore[arg-type]


def test_a_written_trajectory_reads_back_as_written(tmp_path: Path) -> None:
    path = tmp_path / "poses.tum"
    write_tum(path, KEYS, POSES, ["made by a test"])
    assert path.read_text().startswith("# made by a test\n# timestamp tx ty tz qx qy qz qw\n")
    read = read_tum(path)
    assert read.keys.tolist() == KEYS  # exact: every number written in its shortest round-trip form
    np.testing.assert_allclose(read.poses, POSES, rtol=0, atol=1e-15)
    write_tum(tmp_path / "again.tum", read.keys, read.poses)
    np.testing.assert_allclose(read_tum(tmp_path / "again.tum").poses, POSES, rtol=0, atol=1e-15)
    for pose in read.poses:
        validate_pose(pose)


def test_lines_are_sorted_matched_within_a_tenth_of_a_millisecond_and_commented(tmp_path: Path) -> None:
    path = tmp_path / "poses.tum"
    path.write_text("# from another tool\n\n2.000050 0 0 1 0 0 0 1\n1.0,0,0,0,0,0,0,2\n")
    read = read_tum(path)
    assert read.keys.tolist() == [1.0, 2.00005]
    np.testing.assert_array_equal(read.find(2.0)[:3, 3], [0, 0, 1])
    np.testing.assert_array_equal(read.find(1.0)[:3, :3], np.eye(3))  # the quaternion normalised
    assert read.find(2.0002) is None and read.find(0.5) is None and read.find(3.0) is None


def test_a_frame_is_keyed_by_its_timestamp_else_its_index(tmp_path: Path) -> None:
    assert frame_key(frame(7, 1.5)) == 1.5
    assert frame_key(frame(7, None)) == 7.0
    assert frame_key(frame(7, 0.0)) == 0.0  # a clock that starts at zero is still a clock
    trajectory = Trajectory(np.array([0.0, 1.0]), np.stack([np.eye(4), np.eye(4)]), "poses.tum")
    assert trajectory.pose_of(frame(1, None)) is not None
    with pytest.raises(ValueError, match=r"^poses.tum has no pose for frame 3 \(timestamp 2.5\)$"):
        trajectory.pose_of(frame(3, 2.5))
    with pytest.raises(ValueError, match=r"^poses.tum has no pose for frame 4$"):
        trajectory.pose_of(frame(4, None))


BAD = {
    "seven fields": ("1 0 0 0 0 0 1", r":3: expected 8 fields \(timestamp tx ty tz qx qy qz qw\), got 7"),
    "nine fields": ("1 0 0 0 0 0 0 1 5", r":3: expected 8 fields .*, got 9"),
    "a word": ("1 0 0 x 0 0 0 1", r":3: not a number \(could not convert string to float: 'x'\)"),
    "nan": ("1 0 nan 0 0 0 0 1", r":3: non-finite value in 1 0 nan 0 0 0 0 1"),
    "inf timestamp": ("inf 0 0 0 0 0 0 1", r":3: non-finite value"),
    "zero quaternion": ("1 0 0 0 0 0 0 0", r":3: the quaternion \(qx qy qz qw\) is zero"),
    "duplicate timestamp": ("0.5 1 0 0 0 0 0 1", r":3: duplicate timestamp 0.5, also on line 2$"),
    "near duplicate": ("0.50001 1 0 0 0 0 0 1",
                       r":3: duplicate timestamp: 0.50001 lies within 0.0001 s of line 2's 0.5$"),
}


@pytest.mark.parametrize("line,message", BAD.values(), ids=BAD.keys())
def test_bad_lines_are_refused_naming_the_file_and_line(tmp_path: Path, line: str, message: str) -> None:
    path = tmp_path / "poses.tum"
    path.write_text(f"# timestamp tx ty tz qx qy qz qw\n0.5 0 0 0 0 0 0 1\n{line}\n")
    with pytest.raises(ValueError, match=f"^{path}{message}"):
        read_tum(path)


def test_a_file_without_poses_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "empty.tum"
    path.write_text("# nothing here\n\n")
    with pytest.raises(ValueError, match=f"^{path}: no poses"):
        read_tum(path)


def test_noise_is_seeded_leaves_the_first_pose_and_has_the_asked_spread() -> None:
    poses = np.repeat(POSES[:1], 4001, axis=0)
    noisy = perturb(poses, 0.01, 0.5, seed=7)
    assert noisy.tolist() == perturb(poses, 0.01, 0.5, seed=7).tolist()
    assert noisy.tolist() != perturb(poses, 0.01, 0.5, seed=8).tolist()
    assert noisy[0].tolist() == poses[0].tolist()
    assert poses.tolist() == np.repeat(POSES[:1], 4001, axis=0).tolist()  # the input is left alone
    shifts = noisy[1:, :3, 3] - poses[1:, :3, 3]
    assert np.abs(shifts.mean(axis=0)).max() < 0.001
    np.testing.assert_allclose(shifts.std(axis=0), 0.01, rtol=0.05)
    distances, angles = pose_errors(noisy[1:], poses[1:])
    assert distances.mean() == pytest.approx(0.01 * math.sqrt(8 / math.pi), rel=0.03)  # chi with 3 degrees
    assert angles.mean() == pytest.approx(0.5 * math.sqrt(2 / math.pi), rel=0.05)  # |N(0, 0.5 deg)|
    for pose in noisy[1:50]:
        validate_pose(pose)
    # the camera turns about its own centre, about axes spread over the whole sphere
    relative = np.einsum("ji,njk->nik", poses[0, :3, :3], noisy[1:, :3, :3])
    axes = np.stack([relative[:, 2, 1] - relative[:, 1, 2], relative[:, 0, 2] - relative[:, 2, 0],
                     relative[:, 1, 0] - relative[:, 0, 1]], axis=1)
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    assert np.abs(axes.mean(axis=0)).max() < 0.05
    np.testing.assert_allclose(np.abs(axes).mean(axis=0), 0.5, atol=0.03)  # uniform: E|x| = 1/2


def test_noise_can_move_the_first_pose_too_with_the_same_draws() -> None:
    kept = perturb(POSES, 0.01, 0.5, seed=1)
    moved = perturb(POSES, 0.01, 0.5, seed=1, keep_first=False)
    assert moved[0].tolist() != POSES[0].tolist()
    assert moved[1:].tolist() == kept[1:].tolist()


def test_no_noise_is_no_change_and_bad_noise_is_refused() -> None:
    np.testing.assert_array_equal(perturb(POSES, 0.0, 0.0, seed=0), POSES)
    with pytest.raises(ValueError, match=r"translation noise must be a finite number >= 0 metres, got -0.01"):
        perturb(POSES, -0.01, 0.5, seed=0)
    with pytest.raises(ValueError, match=r"rotation noise must be a finite number >= 0 degrees, got nan"):
        perturb(POSES, 0.01, math.nan, seed=0)
    with pytest.raises(ValueError, match=r"the noise seed must be >= 0, got -1"):
        perturb(POSES, 0.01, 0.5, seed=-1)


def test_axis_angle_turns_by_the_angle() -> None:
    rotation = axis_angle_matrix(np.array([0.0, 0.0, 1.0]), math.pi / 2)
    np.testing.assert_allclose(rotation @ [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], atol=1e-15)
    _, angles = pose_errors(np.array([np.eye(4)]), np.array([np.eye(4)]))
    assert angles.tolist() == [0.0]


def test_a_rotation_stored_not_quite_orthonormal_is_not_a_turn() -> None:
    pose = np.eye(4)
    pose[:3, :3] = axis_angle_matrix(np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]), 0.7) * 0.99995
    turned = pose.copy()
    turned[:3, :3] = axis_angle_matrix(np.array([1.0, 0.0, 0.0]), math.radians(0.2)) @ pose[:3, :3]
    _, angles = pose_errors(np.array([pose, turned]), np.array([pose, pose]))
    np.testing.assert_allclose(angles, [0.0, 0.2], atol=1e-6)


def test_a_frame_set_gives_the_trajectory_poses(tmp_path: Path) -> None:
    frames = open_frames("synthetic", "synthetic", "0:3", scale=0.25, n_frames=12)
    moved = perturb(POSES, 0.01, 0.5, seed=2)
    write_tum(tmp_path / "moved.tum", KEYS, moved)
    frames.poses = read_tum(tmp_path / "moved.tum")
    assert frames.positions == [0, 1, 2]
    np.testing.assert_allclose(frames.load(2).c2w, moved[2], atol=1e-15)
    assert frames.load(2).color_intrinsics.width == 80
