"""Dataset readers on small fixture folders written here, plus the real 7-Scenes copy when present."""

from __future__ import annotations

from dataclasses import astuple
from pathlib import Path

import cv2
import numpy as np
import pytest

from ogmapping.datasets import FORMATS, open_dataset
from ogmapping.datasets.base import decode_depth
from ogmapping.datasets.replica import Replica
from ogmapping.datasets.scannet import ScanNet
from ogmapping.datasets.sevenscenes import MEASURED_BASELINE, SevenScenes
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.datasets.tum import TUM, associate_unique
from ogmapping.frames.camera import Intrinsics


def random_pose(rng: np.random.Generator) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    if np.linalg.det(q) < 0:
        q[:, 0] *= -1
    pose = np.eye(4)
    pose[:3, :3] = q
    pose[:3, 3] = rng.uniform(-2, 2, 3)
    return pose


def write_color(path: Path, width: int, height: int, value: int) -> None:
    """A flat colour image (flat so JPEG keeps it nearly exact), RGB = (value, 2*value, 3*value) % 256."""
    path.parent.mkdir(parents=True, exist_ok=True)
    rgb = np.zeros((height, width, 3), np.uint8)
    rgb[:] = (value % 256, (2 * value) % 256, (3 * value) % 256)
    assert cv2.imwrite(str(path), rgb[:, :, ::-1].copy())


def write_depth(path: Path, raw: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), raw.astype(np.uint16))


def depth_pattern(width: int, height: int, metres: float, scale: float) -> np.ndarray:
    """Raw depth at ``metres`` with a 0 and a 65535 invalid marker in the first row."""
    raw = np.full((height, width), round(metres * scale), np.uint16)
    raw[0, 0] = 0
    raw[0, 1] = 65535
    return raw


def write_pose(path: Path, pose: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, pose)


# 7-Scenes ---------------------------------------------------------------------------------------


@pytest.fixture
def sevenscenes_dir(tmp_path: Path) -> tuple[Path, list[np.ndarray]]:
    root = tmp_path / "seq" / "data"
    rng = np.random.default_rng(1)
    poses = []
    for number in (10, 2, 0):  # written out of order on purpose
        stem = f"frame-{number:06d}"
        write_color(root / f"{stem}.color.jpg", 64, 48, 40 + number)
        write_depth(root / f"{stem}.depth.png", depth_pattern(64, 48, 1.0 + number / 10, 1000.0))
        pose = random_pose(rng)
        write_pose(root / f"{stem}.pose.txt", pose)
        poses.append((number, pose))
    np.savetxt(root / "camera-intrinsics.txt", np.array([[58.5, 0, 32], [0, 58.5, 24], [0, 0, 1]]))
    # A frame without a pose is not a complete frame and is left out.
    write_depth(root / "frame-000011.depth.png", depth_pattern(64, 48, 1.0, 1000.0))
    return tmp_path / "seq", [pose for _, pose in sorted(poses, key=lambda p: p[0])]


def test_sevenscenes_reads_sorted_frames(sevenscenes_dir: tuple[Path, list[np.ndarray]]) -> None:
    path, poses = sevenscenes_dir
    source = open_dataset(str(path))
    assert isinstance(source, SevenScenes)
    assert len(source) == 3
    for position, number in enumerate((0, 2, 10)):
        frame = source[position]
        assert frame.index == position
        np.testing.assert_allclose(frame.c2w @ frame.depth_to_color, poses[position], atol=1e-12)  # the depth camera's
        assert frame.c2w.dtype == np.float64
        assert frame.timestamp == pytest.approx(number / 30.0)
        assert frame.rgb.dtype == np.float32 and frame.rgb.shape == (48, 64, 3)
        np.testing.assert_allclose(frame.rgb[10, 10], np.array([40 + number, 80 + 2 * number, 120 + 3 * number]) / 255,
                                   atol=3 / 255)
        assert frame.depth.dtype == np.float32
        assert frame.depth[0, 0] == 0.0 and frame.depth[0, 1] == 0.0  # 0 and 65535 markers
        assert frame.depth[5, 5] == pytest.approx(1.0 + number / 10)
        assert not frame.registered


def test_sevenscenes_intrinsics_conventions(sevenscenes_dir: tuple[Path, list[np.ndarray]]) -> None:
    path, _ = sevenscenes_dir
    measured = SevenScenes(path)
    # The file's K (integer pixel centres) moves by +0.5 to our convention.
    assert measured.depth_intrinsics == Intrinsics(58.5, 58.5, 32.5, 24.5, 64, 48)
    # Measured colour K is given at 640x480 (526.5, 321.625, 238.125) and scaled to the image size.
    assert astuple(measured.intrinsics) == pytest.approx((52.65, 52.65, 32.2125, 23.8625, 64, 48))
    same = SevenScenes(path, color_intrinsics="depth")
    assert same.intrinsics == same.depth_intrinsics
    assert same[0].registered
    explicit = SevenScenes(path, color_intrinsics=(50.0, 51.0, 30.0, 22.0))
    assert explicit.intrinsics == Intrinsics(50.0, 51.0, 30.5, 22.5, 64, 48)
    assert explicit[0].depth_to_color is None
    as_array = SevenScenes(path, color_intrinsics=np.array([50.0, 51.0, 30.0, 22.0]))
    assert as_array.intrinsics == explicit.intrinsics and as_array[0].depth_to_color is None
    with pytest.raises(ValueError, match="color_intrinsics"):
        SevenScenes(path, color_intrinsics="guess")


def test_sevenscenes_measured_colour_camera_sits_beside_the_depth_camera(
    sevenscenes_dir: tuple[Path, list[np.ndarray]],
) -> None:
    path, _ = sevenscenes_dir
    measured, same = SevenScenes(path)[1], SevenScenes(path, color_intrinsics="depth")[1]
    # The files' poses are the depth camera's: a depth-camera point lands on the same world point
    # through either camera's pose.
    point = np.array([0.3, -0.2, 1.5, 1.0])
    np.testing.assert_allclose(measured.c2w @ measured.depth_to_color @ point, same.c2w @ point, atol=1e-12)
    np.testing.assert_allclose(measured.depth_to_color[:3, 3], [-MEASURED_BASELINE, 0.0, 0.0])
    # The colour camera's centre is the baseline along the depth camera's x axis.
    np.testing.assert_allclose(measured.c2w[:3, 3], same.c2w[:3, 3] + MEASURED_BASELINE * same.c2w[:3, 0])


def test_frame_source_indexing(sevenscenes_dir: tuple[Path, list[np.ndarray]]) -> None:
    source = SevenScenes(sevenscenes_dir[0])
    assert source[-1].index == 2
    assert [frame.index for frame in source] == [0, 1, 2]
    with pytest.raises(IndexError):
        source[3]


@pytest.mark.realdata
def test_sevenscenes_real_data(seven_scenes: Path) -> None:
    source = open_dataset(str(seven_scenes))
    assert isinstance(source, SevenScenes)
    assert len(source) == 600
    assert source.depth_intrinsics == Intrinsics(585.0, 585.0, 320.5, 240.5, 640, 480)
    assert source.intrinsics == Intrinsics(526.5, 526.5, 322.125, 238.625, 640, 480)
    frame = source[10]
    depth_pose = np.loadtxt(seven_scenes / "data" / "frame-000010.pose.txt")
    np.testing.assert_allclose(frame.c2w @ frame.depth_to_color, depth_pose, atol=1e-12)
    valid = frame.depth[frame.depth > 0]
    assert frame.depth.shape == (480, 640) and frame.rgb.shape == (480, 640, 3)
    assert valid.min() > 0.7 and valid.max() < 4.5  # 65535 never leaks through as 65.5 m
    assert 0.02 < (frame.depth == 0).mean() < 0.5


# TUM --------------------------------------------------------------------------------------------


@pytest.fixture
def tum_dir(tmp_path: Path) -> Path:
    root = tmp_path / "rgbd_dataset_freiburg1_xyz"
    rgb_times = ["1.000", "1.033", "1.067", "1.100", "1.200"]
    depth_times = ["1.004", "1.031", "1.036", "1.098", "1.201"]
    rgb_lines = ["# color images", "# timestamp filename"]
    depth_lines = ["# depth maps", "# timestamp filename"]
    for i, stamp in enumerate(rgb_times):
        write_color(root / "rgb" / f"{stamp}.png", 32, 24, 10 * i)
        rgb_lines.append(f"{stamp} rgb/{stamp}.png")
    for i, stamp in enumerate(depth_times):
        write_depth(root / "depth" / f"{stamp}.png", depth_pattern(32, 24, 0.5 + i * 0.25, 5000.0))
        depth_lines.append(f"{stamp} depth/{stamp}.png")
    half = np.sqrt(0.5)
    truth = [
        "# ground truth trajectory",
        "# timestamp tx ty tz qx qy qz qw",
        "0.999 1 2 3 0 0 0 1",
        f"1.032 0.5 0 0 0 0 {half} {half}",
        "1.066 0 0 0 0 0 0 1",
        "1.101 0 0 1 1 0 0 0",
    ]
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    (root / "groundtruth.txt").write_text("\n".join(truth) + "\n")
    return root


def test_tum_association_and_poses(tum_dir: Path) -> None:
    source = open_dataset(str(tum_dir))
    assert isinstance(source, TUM)
    # 1.067 has no depth within 0.02 s, 1.200 no pose: three frames remain.
    assert [frame.timestamp for frame in source] == pytest.approx([1.000, 1.033, 1.100])
    first, second, third = source[0], source[1], source[2]
    assert first.depth[5, 5] == pytest.approx(0.5)  # depth 1.004
    assert second.depth[5, 5] == pytest.approx(0.75)  # depth 1.031, closer than 1.036
    assert third.depth[5, 5] == pytest.approx(1.25)  # depth 1.098
    assert first.depth[0, 0] == 0 and first.depth[0, 1] == 0
    np.testing.assert_allclose(first.c2w[:3, 3], [1, 2, 3])
    np.testing.assert_allclose(second.c2w[:3, :3], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12)
    np.testing.assert_allclose(third.c2w[:3, :3], np.diag([1.0, -1.0, -1.0]), atol=1e-12)
    np.testing.assert_allclose(second.rgb[3, 3], np.array([10, 20, 30]) / 255, atol=1e-6)
    assert first.registered


def test_tum_intrinsics(tum_dir: Path) -> None:
    default = TUM(tum_dir).intrinsics
    scale = 32 / 640
    assert (default.fx, default.fy) == pytest.approx((517.3 * scale, 516.5 * scale))
    assert (default.cx, default.cy) == pytest.approx(((318.6 + 0.5) * scale, (255.3 + 0.5) * scale))
    assert TUM(tum_dir, intrinsics=(20.0, 21.0, 15.5, 11.5)).intrinsics == Intrinsics(20, 21, 16, 12, 32, 24)
    own = Intrinsics(20, 21, 16, 12, 32, 24)
    assert TUM(tum_dir, intrinsics=own).intrinsics is own


def test_tum_associate_unique_prefers_closest_pair() -> None:
    pairs = associate_unique(np.array([0.0, 0.01, 0.5]), np.array([0.006, 0.9]), 0.02)
    assert pairs == [(1, 0)]


# Replica ----------------------------------------------------------------------------------------


@pytest.fixture
def replica_dir(tmp_path: Path) -> tuple[Path, np.ndarray]:
    root = tmp_path / "room0"
    rng = np.random.default_rng(2)
    poses = np.stack([random_pose(rng) for _ in range(3)])
    for i in range(3):
        write_color(root / "results" / f"frame{i:06d}.jpg", 60, 34, 20 * i)
        write_depth(root / "results" / f"depth{i:06d}.png", depth_pattern(60, 34, 2.0, 6553.5))
    np.savetxt(root / "traj.txt", poses.reshape(3, 16))
    return root, poses


def test_replica_reader(replica_dir: tuple[Path, np.ndarray]) -> None:
    root, poses = replica_dir
    source = open_dataset(str(root))
    assert isinstance(source, Replica)
    assert len(source) == 3
    for i in range(3):
        np.testing.assert_allclose(source[i].c2w, poses[i], atol=1e-12)
    frame = source[1]
    assert frame.depth[5, 5] == pytest.approx(2.0, abs=1e-4)
    assert frame.depth[0, 0] == 0 and frame.depth[0, 1] == 0
    # (600, 600, 599.5, 339.5) at 1200x680 is centred once shifted; scaled to 60x34.
    assert astuple(source.intrinsics) == pytest.approx((30.0, 30.0, 30.0, 17.0, 60, 34))
    assert frame.registered
    explicit = Replica(root, intrinsics=(30.0, 30.0, 29.5, 16.5))
    assert explicit.intrinsics == Intrinsics(30.0, 30.0, 30.0, 17.0, 60, 34)


# ScanNet ----------------------------------------------------------------------------------------


@pytest.fixture
def scannet_dir(tmp_path: Path) -> tuple[Path, dict[int, np.ndarray]]:
    root = tmp_path / "scene0000_00"
    rng = np.random.default_rng(3)
    poses = {}
    for number in (0, 2, 9, 10):
        write_color(root / "color" / f"{number}.jpg", 40, 30, 10 * number)
        write_depth(root / "depth" / f"{number}.png", depth_pattern(20, 15, 1.0 + number / 100, 1000.0))
        pose = random_pose(rng)
        if number == 2:
            pose[:] = -np.inf  # ScanNet's mark of a tracking failure
        write_pose(root / "pose" / f"{number}.txt", pose)
        poses[number] = pose
    (root / "intrinsic").mkdir()
    color_k = np.array([[36.0, 0, 19.5, 0], [0, 36.5, 14.5, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    depth_k = np.array([[18.0, 0, 9.5, 0], [0, 18.0, 7.0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    np.savetxt(root / "intrinsic" / "intrinsic_color.txt", color_k)
    np.savetxt(root / "intrinsic" / "intrinsic_depth.txt", depth_k)
    return root, poses


def test_scannet_skips_invalid_poses_and_sorts_numerically(scannet_dir: tuple[Path, dict[int, np.ndarray]]) -> None:
    root, poses = scannet_dir
    source = open_dataset(str(root))
    assert isinstance(source, ScanNet)
    assert len(source) == 3
    for position, number in enumerate((0, 9, 10)):
        frame = source[position]
        assert frame.index == position
        np.testing.assert_allclose(frame.c2w, poses[number], atol=1e-12)
        assert frame.depth[5, 5] == pytest.approx(1.0 + number / 100)
        assert frame.depth[0, 0] == 0 and frame.depth[0, 1] == 0
        np.testing.assert_allclose(frame.rgb[5, 5, 0], (10 * number % 256) / 255, atol=3 / 255)
    frame = source[0]
    assert frame.rgb.shape == (30, 40, 3) and frame.depth.shape == (15, 20)
    assert frame.color_intrinsics == Intrinsics(36.0, 36.5, 20.0, 15.0, 40, 30)
    assert frame.depth_intrinsics == Intrinsics(18.0, 18.0, 10.0, 7.5, 20, 15)
    assert not frame.registered


# Shared decoding and detection -------------------------------------------------------------------


def test_decode_depth_invalid_markers() -> None:
    raw = np.array([[0, 65535, 1000, 2500]], np.uint16)
    np.testing.assert_allclose(decode_depth(raw, 1000.0), [[0, 0, 1.0, 2.5]])
    floats = np.array([[np.nan, np.inf, -1.0, 1.5]], np.float32)
    np.testing.assert_allclose(decode_depth(floats, 1.0), [[0, 0, 0, 1.5]])


def test_auto_detection_picks_each_format(
    sevenscenes_dir: tuple[Path, list[np.ndarray]],
    tum_dir: Path,
    replica_dir: tuple[Path, np.ndarray],
    scannet_dir: tuple[Path, dict[int, np.ndarray]],
) -> None:
    assert isinstance(open_dataset(str(sevenscenes_dir[0] / "data")), SevenScenes)
    assert isinstance(open_dataset(str(tum_dir), format="tum"), TUM)
    assert isinstance(open_dataset(str(replica_dir[0]), format="replica"), Replica)
    assert isinstance(open_dataset(str(scannet_dir[0]), format="scannet"), ScanNet)
    with pytest.raises(ValueError, match="no TUM"):
        open_dataset(str(replica_dir[0]), format="tum")


def test_synthetic_through_open_dataset() -> None:
    source = open_dataset("synthetic", n_frames=4, width=32, height=24, seed=5)
    assert isinstance(source, SyntheticSource)
    assert len(source) == 4 and source[0].rgb.shape == (24, 32, 3)
    assert isinstance(open_dataset("", format="synthetic", n_frames=2), SyntheticSource)


def test_errors_name_what_was_looked_for(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="does not exist"):
        open_dataset(str(tmp_path / "missing"))
    with pytest.raises(ValueError, match="does not exist"):
        open_dataset(str(tmp_path / "missing"), format="tum")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=r"frame-\*\.depth\.png.*rgb\.txt.*traj\.txt.*color/"):
        open_dataset(str(tmp_path / "empty"))
    with pytest.raises(ValueError, match="7scenes, tum"):
        open_dataset(str(tmp_path), format="kitti")
    assert "synthetic" in FORMATS
