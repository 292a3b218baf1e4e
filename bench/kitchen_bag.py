"""A ROS 2 (MCAP) bag from 7-Scenes RedKitchen, laid out like a RealSense on a robot, for trying ``--bag``.

    python bench/kitchen_bag.py OUT [--frames 60] [--data ../shared/data/7scenes-redkitchen]

Topics: JPEG colour (``/camera/color/image_raw/compressed``), compressedDepth PNG
(``/camera/depth/image_rect_raw/compressedDepth``), both cameras' ``camera_info`` (7-Scenes' measured
colour K and its depth K), an IR camera (mono8, so the colour topic needs ``--color-topic``), and TF:
``map -> odom``, ``base_link -> camera_link -> camera_color_optical_frame`` and the depth camera
beside it (``camera_color_optical_frame -> camera_depth_optical_frame``, the reader's measured
baseline) on ``/tf_static``, ``odom -> base_link`` moving on ``/tf`` so that the colour camera's pose is
the recorded one.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

from rosbag_writer import BagRecorder, compressed_depth_16

from ogmapping.datasets.rosbag.transforms import invert
from ogmapping.datasets.sevenscenes import MEASURED_COLOR_K, SevenScenes
from ogmapping.frames.rotation import quaternion_pose

T0 = 1_700_000_000 * 10**9
PERIOD = 33_333_333
BASE_CAMERA = quaternion_pose(np.array([0.1, 0.0, 1.2]), np.array([0.0, 0.0, 0.0, 1.0]))
OPTICAL = quaternion_pose(np.zeros(3), np.array([-0.5, 0.5, -0.5, 0.5]))
CAMERA = "camera_color_optical_frame"
DEPTH_CAMERA = "camera_depth_optical_frame"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", help="the bag folder to create")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared/data/7scenes-redkitchen"))
    args = parser.parse_args()
    source = SevenScenes(args.data)
    depth_k = source.depth_intrinsics
    with BagRecorder(Path(args.out), ros2=True) as bag:
        bag.write("/tf_static", T0, bag.tf(T0, [("map", "odom", np.eye(4)), ("base_link", "camera_link", BASE_CAMERA),
                                               ("camera_link", CAMERA, OPTICAL),
                                               (CAMERA, DEPTH_CAMERA, source.depth_to_color)]))
        for i in range(args.frames):
            frame, t = source[i], T0 + i * PERIOD
            rgb = (frame.rgb * 255).round().astype(np.uint8)
            depth = (frame.depth * 1000).round().astype(np.uint16)
            jpeg = cv2.imencode(".jpg", rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
            bag.write("/camera/color/image_raw/compressed", t,
                      bag.compressed(t, CAMERA, jpeg, "rgb8; jpeg compressed bgr8"))
            bag.write("/camera/color/camera_info", t, bag.camera_info(t, CAMERA, 640, 480, MEASURED_COLOR_K))
            bag.write("/camera/depth/image_rect_raw/compressedDepth", t,
                      bag.compressed(t, DEPTH_CAMERA, compressed_depth_16(depth), "16UC1; compressedDepth png"))
            bag.write("/camera/depth/camera_info", t, bag.camera_info(
                t, DEPTH_CAMERA, 640, 480, (depth_k.fx, depth_k.fy, depth_k.cx - 0.5, depth_k.cy - 0.5)))
            bag.write("/tf", t, bag.tf(t, [("odom", "base_link", frame.c2w @ invert(BASE_CAMERA @ OPTICAL))]))
            bag.write("/camera/infra1/image_rect_raw", t,
                      bag.image(t, "camera_infra1_optical_frame", rgb[:, :, 1], "mono8"))
    print(f"wrote {args.out}: {args.frames} frames")


if __name__ == "__main__":
    main()
