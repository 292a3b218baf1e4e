"""The web view's world up, from camera poses: the synthetic room's z, the kitchen's gravity, one camera's own."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from ogserver.web.horizon import world_up

from ogmapping.datasets.synthetic import trajectory


def degrees_between(a, b) -> float:
    return math.degrees(math.acos(float(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def test_the_synthetic_rooms_up_is_z_though_its_cameras_look_down() -> None:
    poses = trajectory(40)
    mean_camera_up = -poses[:10, :3, 1].mean(axis=0)
    assert degrees_between(mean_camera_up, [0, 0, 1]) > 5  # what a plain average of the up axes gets wrong
    assert degrees_between(world_up(poses[:10]), [0, 0, 1]) < 4


def test_one_camera_gives_its_own_up_and_none_gives_none() -> None:
    pose = trajectory(3)[1]
    assert degrees_between(world_up(pose[None]), -pose[:3, 1]) < 1e-6
    assert world_up(np.zeros((0, 4, 4))) is None


def test_the_kitchens_up_is_near_its_gravity(seven_scenes: Path) -> None:
    data = seven_scenes / "data"
    poses = np.array([np.loadtxt(data / f"frame-{index:06d}.pose.txt") for index in range(0, 600, 30)])
    gravity = np.loadtxt(data / "gravity-direction.txt")
    # The hand-held camera was rolled 3.6 degrees on average against the table top: the estimate keeps that.
    assert degrees_between(world_up(poses), -gravity) < 7
    assert degrees_between(-poses[:, :3, 1].mean(axis=0), -gravity) > 20  # the plain average leans with the pitch
