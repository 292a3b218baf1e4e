"""How fast the ROS bag reader opens a bag and decodes its frames.

    python bench/bag_read.py --frames 300 [--storage ros1 mcap sqlite3] [--compressed]

Writes a bag per storage into a temporary folder with ``tests/rosbag_writer.py`` (640x480 noise:
rgb8 + 16UC1 raw, or JPEG + compressedDepth PNG with ``--compressed``; camera_info per frame; TF
``odom -> base_link`` at three samples per frame and a static mount), then times ``open_dataset``
(topic discovery, the header index, TF) and one pass decoding every frame. Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from rosbag_writer import BagRecorder, compressed_depth_16

from ogmapping.datasets import open_dataset

T0 = 1_700_000_000 * 10**9
PERIOD = 33_333_333


def write(path: Path, storage: str, frames: int, compressed: bool) -> Path:
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)
    depth = rng.integers(500, 4000, (480, 640)).astype(np.uint16)
    jpeg = cv2.imencode(".jpg", rgb, [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
    with BagRecorder(path, ros2=storage != "ros1", storage=storage) as bag:
        bag.write("/tf_static", T0, bag.tf(T0, [("base_link", "cam_optical_frame", np.eye(4))]))
        for i in range(frames):
            t = T0 + i * PERIOD
            if compressed:
                bag.write("/cam/color/image_raw/compressed", t, bag.compressed(t, "cam_optical_frame", jpeg, "jpeg"))
                bag.write("/cam/depth/image_raw/compressedDepth", t, bag.compressed(
                    t, "cam_optical_frame", compressed_depth_16(depth), "16UC1; compressedDepth png"))
            else:
                bag.write("/cam/color/image_raw", t, bag.image(t, "cam_optical_frame", rgb, "rgb8"))
                bag.write("/cam/depth/image_raw", t, bag.image(t, "cam_optical_frame", depth, "16UC1"))
            bag.write("/cam/color/camera_info", t, bag.camera_info(t, "cam_optical_frame", 640, 480,
                                                                   (525.0, 525.0, 319.5, 239.5)))
            for sample in range(3):
                ts = t + sample * PERIOD // 3
                pose = np.eye(4)
                pose[0, 3] = (ts - T0) * 1e-9
                bag.write("/tf", ts, bag.tf(ts, [("odom", "base_link", pose)]))
    return path


def size_mb(path: Path) -> float:
    files = [path] if path.is_file() else list(path.iterdir())
    return sum(f.stat().st_size for f in files) / 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=300)
    storages = ["ros1", "mcap", "sqlite3"]
    parser.add_argument("--storage", nargs="+", default=storages, choices=storages)
    parser.add_argument("--compressed", action="store_true", help="JPEG colour and compressedDepth instead of raw")
    args = parser.parse_args()
    print("| storage | images | MB | open s | decode frames/s |")
    print("|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as folder:
        for storage in args.storage:
            path = write(Path(folder) / (f"{storage}.bag" if storage == "ros1" else storage), storage, args.frames,
                         args.compressed)
            tic = time.perf_counter()
            source = open_dataset(str(path), "bag")
            opened = time.perf_counter() - tic
            tic = time.perf_counter()
            for _ in source:
                pass
            decode = len(source) / (time.perf_counter() - tic)
            kind = "JPEG + compressedDepth" if args.compressed else "rgb8 + 16UC1"
            print(f"| {storage} | {kind} | {size_mb(path):.0f} | {opened:.2f} | {decode:.0f} |")


if __name__ == "__main__":
    main()
