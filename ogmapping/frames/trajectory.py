"""Camera trajectories in TUM format, and seeded pose noise to test mapping from imperfect poses.

A TUM trajectory file holds one pose a line, ``timestamp tx ty tz qx qy qz qw``, with ``#`` comment
lines: the camera-to-world pose (``c2w``, metres, OpenCV camera axes as in ``ogmapping.frames.camera``),
its rotation as a quaternion in (x, y, z, w) order. A frame's key in such a file is its ``timestamp``
(seconds) when its source gives one, else its index in the source (every bundled reader gives a
timestamp). Keys match within ``KEY_TOLERANCE``, so files written with microsecond precision by other
tools still match; ``write_tum`` writes every number exactly (shortest round-trip form). A quaternion holds
only rotations: data whose rotation matrices are not orthonormal to float precision (7-Scenes' are off by
up to 1e-4) come back as a nearby rotation, up to 6e-5 off; Replica's and the synthetic poses come back
within 1e-15.

Numpy only, so the torch-free client can read and write trajectories too.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ogmapping.frames.frame import Frame
from ogmapping.frames.rotation import axis_angle_matrix, matrix_to_quaternion, quaternion_pose

KEY_TOLERANCE = 1e-4  # seconds: far below any camera's frame interval, above six-decimal rounding
COLUMNS = "timestamp tx ty tz qx qy qz qw"
MIN_QUATERNION_NORM = 1e-9


def frame_key(frame: Frame) -> float:
    """A frame's key in a trajectory file: its timestamp, else its index in its source."""
    return float(frame.timestamp) if frame.timestamp is not None else float(frame.index)


def describe(frame: Frame) -> str:
    """The frame as a message names it: index and, where it has one, timestamp."""
    stamp = f" (timestamp {frame.timestamp!r})" if frame.timestamp is not None else ""
    return f"frame {frame.index}{stamp}"


@dataclass(frozen=True)
class Trajectory:
    """Poses keyed by timestamp (or frame index), sorted by key; ``name`` says where they came from."""

    keys: np.ndarray  # (N,) float64, strictly increasing
    poses: np.ndarray  # (N, 4, 4) float64 camera-to-world
    name: str

    def find(self, key: float) -> np.ndarray | None:
        """The pose whose key lies nearest ``key`` within ``KEY_TOLERANCE``, or None."""
        right = int(np.searchsorted(self.keys, key))
        nearby = [i for i in (right - 1, right) if 0 <= i < len(self.keys)]
        if not nearby:
            return None
        best = min(nearby, key=lambda i: abs(self.keys[i] - key))
        return self.poses[best].copy() if abs(self.keys[best] - key) <= KEY_TOLERANCE else None

    def pose_of(self, frame: Frame) -> np.ndarray:
        """The pose for ``frame`` (matched by ``frame_key``); ValueError naming the frame and file if none."""
        pose = self.find(frame_key(frame))
        if pose is None:
            raise ValueError(f"{self.name} has no pose for {describe(frame)}")
        return pose


def parse_line(fields: list[str], where: str) -> tuple[float, np.ndarray]:
    """(key, c2w) of one data line's fields; ValueError starting with ``where`` (file:line) on bad input."""
    if len(fields) != 8:
        raise ValueError(f"{where}: expected 8 fields ({COLUMNS}), got {len(fields)}")
    try:
        values = [float(field) for field in fields]
    except ValueError as error:
        raise ValueError(f"{where}: not a number ({error})") from error
    if not all(math.isfinite(value) for value in values):
        raise ValueError(f"{where}: non-finite value in {' '.join(fields)}")
    if math.hypot(*values[4:]) < MIN_QUATERNION_NORM:
        raise ValueError(f"{where}: the quaternion (qx qy qz qw) is zero, it gives no rotation")
    return values[0], quaternion_pose(values[1:4], values[4:])


def read_tum(path: str | Path) -> Trajectory:
    """The trajectory in a TUM file; ValueError naming the file and line for anything it cannot use,
    timestamps closer than ``KEY_TOLERANCE`` included (no frame could tell them apart)."""
    path = Path(path)
    entries: list[tuple[float, int, np.ndarray]] = []
    for number, line in enumerate(path.read_text().splitlines(), start=1):
        fields = line.replace(",", " ").split()
        if not fields or fields[0].startswith("#"):
            continue
        key, pose = parse_line(fields, f"{path}:{number}")
        entries.append((key, number, pose))
    if not entries:
        raise ValueError(f"{path}: no poses (expected lines of {COLUMNS})")
    entries.sort(key=lambda entry: (entry[0], entry[1]))
    for (key, first, _), (later_key, second, _) in itertools.pairwise(entries):
        if later_key - key <= KEY_TOLERANCE:
            (line, stamp), (other, other_stamp) = sorted([(first, key), (second, later_key)], reverse=True)
            if stamp == other_stamp:
                raise ValueError(f"{path}:{line}: duplicate timestamp {stamp!r}, also on line {other}")
            raise ValueError(f"{path}:{line}: duplicate timestamp: {stamp!r} lies within {KEY_TOLERANCE} s of "
                             f"line {other}'s {other_stamp!r}")
    keys = np.array([key for key, _, _ in entries], dtype=np.float64)
    return Trajectory(keys, np.stack([pose for _, _, pose in entries]), str(path))


def format_pose(key: float, pose: np.ndarray) -> str:
    """One TUM line, every number in its shortest exact form."""
    qx, qy, qz, qw = matrix_to_quaternion(pose[:3, :3])
    tx, ty, tz = pose[:3, 3]
    return " ".join(repr(float(value)) for value in (key, tx, ty, tz, qx, qy, qz, qw))


def write_tum(
    path: str | Path, keys: Sequence[float], poses: Iterable[np.ndarray], comments: Sequence[str] = (),
) -> None:
    """Write poses as a TUM trajectory, with ``comments`` (one a line) and the column names first."""
    header = [f"# {comment}" for comment in comments] + [f"# {COLUMNS}"]
    body = [format_pose(key, np.asarray(pose, dtype=np.float64)) for key, pose in zip(keys, poses, strict=True)]
    Path(path).write_text("\n".join(header + body) + "\n")


def perturb(
    poses: np.ndarray, translation_std_m: float, rotation_std_deg: float, seed: int, keep_first: bool = True,
) -> np.ndarray:
    """Poses moved by seeded noise, as odometry would give them.

    Each camera centre moves by Gaussian noise of ``translation_std_m`` per world axis; each camera turns
    about its own centre, about an axis drawn uniformly on the sphere, by an angle drawn from
    N(0, ``rotation_std_deg``). The draws for pose i do not depend on ``keep_first``, which leaves the
    first pose exact (the map keeps its frame). Returns a new (N, 4, 4) float64 array.
    """
    if not (math.isfinite(translation_std_m) and translation_std_m >= 0):
        raise ValueError(f"translation noise must be a finite number >= 0 metres, got {translation_std_m}")
    if not (math.isfinite(rotation_std_deg) and rotation_std_deg >= 0):
        raise ValueError(f"rotation noise must be a finite number >= 0 degrees, got {rotation_std_deg}")
    if seed < 0:
        raise ValueError(f"the noise seed must be >= 0, got {seed}")
    poses = np.array(poses, dtype=np.float64)
    count = len(poses)
    rng = np.random.default_rng(seed)
    shifts = rng.normal(0.0, translation_std_m, (count, 3))
    axes = rng.normal(size=(count, 3))
    angles = np.radians(rng.normal(0.0, rotation_std_deg, count))
    for i in range(1 if keep_first else 0, count):
        axis = axes[i] / np.linalg.norm(axes[i])
        poses[i, :3, :3] = poses[i, :3, :3] @ axis_angle_matrix(axis, float(angles[i]))
        poses[i, :3, 3] += shifts[i]
    return poses


def pose_errors(estimate: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pose: the camera centre's distance (metres) and the rotation angle between them (degrees).

    The angle is that of the rotation nearest to the relative one: datasets store rotations that are
    not quite orthonormal (7-Scenes' KinectFusion poses have a squared norm of 2.9997 instead of 3),
    which the trace alone reads as a degree's turn of a pose against itself."""
    estimate, truth = np.asarray(estimate, dtype=np.float64), np.asarray(truth, dtype=np.float64)
    distances = np.linalg.norm(estimate[:, :3, 3] - truth[:, :3, 3], axis=1)
    relative = np.einsum("nji,njk->nik", truth[:, :3, :3], estimate[:, :3, :3])
    left, _, right = np.linalg.svd(relative)
    left[:, :, 2] *= np.sign(np.linalg.det(left @ right))[:, None]  # a rotation, not a reflection
    nearest = left @ right
    cosines = np.clip((np.trace(nearest, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return distances, np.degrees(np.arccos(cosines))
