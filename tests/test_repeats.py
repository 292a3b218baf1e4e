"""Captures stored twice in a 7-Scenes folder: each image is seen from the pose of its own time, a depth pixel
still lands on the world point its pose gives it, and a frame repeated whole, a gap in the numbering or
``repeats="as-recorded"`` leaves the files' poses as they are."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from ogmapping.datasets.sevenscenes import SevenScenes
from ogmapping.frames.rotation import axis_angle_matrix, interpolate_pose

POINT = np.array([0.3, -0.2, 1.5, 1.0])  # a point in the depth camera


def moving_pose(number: int) -> np.ndarray:
    """The depth camera along x at 1 cm a frame, turning half a degree a frame about y."""
    pose = np.eye(4)
    pose[:3, :3] = axis_angle_matrix(np.array([0.0, 1.0, 0.0]), np.radians(0.5 * number))
    pose[:3, 3] = [0.01 * number, 0.0, 1.0]
    return pose


def write_pose(path: Path, pose: np.ndarray) -> None:
    np.savetxt(path, pose, fmt="%.17g")


def recording(root: Path, numbers: list[int]) -> None:
    """Frames with a colour and a depth image of their own (PNG, millimetre depth) and the depth camera's poses."""
    for number in numbers:
        stem = f"frame-{number:06d}"
        assert cv2.imwrite(str(root / f"{stem}.color.png"), np.full((24, 32, 3), 10 * number + 5, np.uint8))
        assert cv2.imwrite(str(root / f"{stem}.depth.png"), np.full((24, 32), 1000 + 50 * number, np.uint16))
        write_pose(root / f"{stem}.pose.txt", moving_pose(number))


def repeat(root: Path, number: int, kind: str) -> None:
    """Frame ``number``'s ``kind`` image ("color" or "depth") replaced by the one before; a repeated depth
    image also takes the pose before, as tracking on it would have given."""
    shutil.copyfile(root / f"frame-{number - 1:06d}.{kind}.png", root / f"frame-{number:06d}.{kind}.png")
    if kind == "depth":
        write_pose(root / f"frame-{number:06d}.pose.txt", moving_pose(number - 1))


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    root = tmp_path / "seq"
    root.mkdir()
    recording(root, list(range(8)))
    repeat(root, 2, "color")  # colour alone: frame 1's image
    repeat(root, 4, "depth")  # depth alone: frame 3's image and pose
    repeat(root, 5, "color")  # colour after a repeated depth: frame 4's image
    repeat(root, 7, "color")
    repeat(root, 7, "depth")  # both: frame 6 whole
    return root


@pytest.mark.parametrize("colour", ["measured", "depth"])
def test_each_image_is_seen_from_the_pose_of_its_time(folder: Path, colour: str) -> None:
    retimed = SevenScenes(folder, color_intrinsics=colour)
    recorded = SevenScenes(folder, color_intrinsics=colour, repeats="as-recorded")
    halfway = interpolate_pose(moving_pose(3), moving_pose(5), 0.5)
    expected_depth_poses = {2: moving_pose(1), 4: halfway, 5: halfway}  # where each colour image was taken
    for position in range(8):
        frame, files = retimed[position], recorded[position]
        assert np.array_equal(frame.rgb, files.rgb) and np.array_equal(frame.depth, files.depth)
        if position not in expected_depth_poses:
            np.testing.assert_array_equal(frame.c2w, files.c2w)
            continue
        # The colour camera moves with the depth camera it sits beside; a depth pixel still lands on the
        # world point of the files' pose for its depth image.
        shift = expected_depth_poses[position] @ np.linalg.inv(moving_pose(position if position != 4 else 3))
        np.testing.assert_allclose(frame.c2w, shift @ files.c2w, atol=1e-12)
        np.testing.assert_allclose(frame.c2w @ frame.depth_to_color @ POINT,
                                   files.c2w @ (np.eye(4) if files.depth_to_color is None
                                                else files.depth_to_color) @ POINT, atol=1e-12)


def test_a_repeated_colour_image_takes_the_colour_pose_of_the_frame_it_repeats(folder: Path) -> None:
    source = SevenScenes(folder)
    np.testing.assert_allclose(source[2].c2w, source[1].c2w, atol=1e-12)
    np.testing.assert_allclose(source[5].c2w, source[4].c2w, atol=1e-12)


def test_a_gap_in_the_numbering_is_no_repeat(tmp_path: Path) -> None:
    root = tmp_path / "gap"
    root.mkdir()
    recording(root, [0, 1, 3])
    shutil.copyfile(root / "frame-000001.color.png", root / "frame-000003.color.png")
    source = SevenScenes(root, repeats="retimed")
    np.testing.assert_array_equal(source[2].c2w, SevenScenes(root, repeats="as-recorded")[2].c2w)


def test_an_unknown_repeats_option_is_refused_by_name(folder: Path) -> None:
    with pytest.raises(ValueError, match="repeats must be one of retimed, as-recorded, got 'drop'"):
        SevenScenes(folder, repeats="drop")
