"""Command-line flags shared by ``ogmap`` and ``ogclient``: dataset, config and camera.

Free of torch, so the client's commands parse them without loading the engine.
"""

from __future__ import annotations

import argparse
from dataclasses import fields
from typing import Any

from ogmapping.config import PRESETS
from ogmapping.datasets import FORMATS, is_bag
from ogmapping.datasets.rosbag.options import BagOptions
from ogmapping.frames.camera import Intrinsics
from ogmapping.quality.evaluation import FrameSet, open_frames


def add_dataset_arguments(parser: argparse.ArgumentParser) -> None:
    """The dataset flags shared by ``ogmap run`` and ``ogclient stream/eval``, with the ROS bag ones."""
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument("--data", help="dataset folder, or the folder above it (the frames in its data/ or one "
                        "other subfolder), or 'synthetic', or a ROS bag")
    source.add_argument("--bag", metavar="PATH", help="a ROS 1 .bag, or a ROS 2 bag (folder, .mcap or .db3); "
                        "same as --data PATH --format bag (see docs/robots.md)")
    parser.add_argument("--format", default="auto", choices=FORMATS, help="dataset layout (default: detect)")
    parser.add_argument("--frames", default=None, metavar="START:END",
                        help="positions in the sorted frame list to use (default: all)")
    parser.add_argument("--stride", type=int, default=1, help="stream every N-th frame (default 1)")
    parser.add_argument("--scale", type=float, default=1.0, help="image scale, e.g. 0.5 for 320x240 (default 1)")
    add_bag_arguments(parser)


def add_bag_arguments(parser: argparse.ArgumentParser) -> None:
    """Topic, frame and timing choices for a bag; each defaults to the bag's only candidate."""
    bag = parser.add_argument_group(
        "ROS bags (--bag)", "Each topic defaults to the bag's only one of its kind; a bag where that is ambiguous "
        "is refused with a list of its topics. Image frames are ROS optical frames (x right, y down, z forward), "
        "OpenCV's axes.")
    bag.add_argument("--color-topic", help="sensor_msgs/Image (rgb8, bgr8, rgba8, bgra8, mono8) or CompressedImage")
    bag.add_argument("--depth-topic", help="sensor_msgs/Image (16UC1 mm, 32FC1 m) or CompressedImage (compressedDepth)")
    bag.add_argument("--info-topic", help="colour CameraInfo (default: camera_info beside the colour topic)")
    bag.add_argument("--depth-info-topic",
                     help="depth CameraInfo (default: camera_info beside the depth topic, else the colour camera's)")
    bag.add_argument("--pose-topic", help="PoseStamped, PoseWithCovarianceStamped or Odometry topic to take poses "
                     "from instead of TF")
    bag.add_argument("--fixed-frame", help="TF world frame for poses (default: the root of the camera's TF tree)")
    bag.add_argument("--camera-frame", help="the camera's optical frame (default: the colour images' frame_id)")
    bag.add_argument("--body-frame", help="frame whose pose --pose-topic (and ogclient stream's --corrected-topic) "
                     "gives (default: Odometry's child_frame_id; PoseStamped: the camera frame); TF mounts the camera "
                     "on it")
    bag.add_argument("--pair-tolerance", type=float, metavar="SECONDS",
                     help=f"largest colour-depth stamp difference to pair (default {DEFAULT_BAG.pair_tolerance})")
    bag.add_argument("--pose-tolerance", type=float, metavar="SECONDS",
                     help="how far an image may lie before the first or after the last pose sample "
                     f"(default {DEFAULT_BAG.pose_tolerance})")


DEFAULT_BAG = BagOptions()
BAG_FLAGS = tuple(field.name for field in fields(BagOptions))


def dataset_source(args: argparse.Namespace) -> tuple[str, str, dict[str, Any]]:
    """(path, format, reader options) from the flags of ``add_dataset_arguments``."""
    bag_options = {name: getattr(args, name) for name in BAG_FLAGS if getattr(args, name, None) is not None}
    if args.bag is not None:
        if args.format not in ("auto", "bag"):
            raise ValueError(f"--bag reads a ROS bag; --format {args.format} does not go with it")
        return args.bag, "bag", bag_options
    if args.format == "bag" or (args.format == "auto" and is_bag(args.data)):
        return args.data, "bag", bag_options
    given = [name for name in BAG_FLAGS if getattr(args, name, None) is not None]
    if given:
        raise ValueError(f"--{given[0].replace('_', '-')} is for ROS bags; {args.data} is not one")
    return args.data, args.format, {}


def open_frame_set(args: argparse.Namespace) -> FrameSet:
    """The frames to stream and hold out, from the flags of ``add_dataset_arguments`` (``--bag`` and its flags
    included)."""
    data, format, options = dataset_source(args)
    return open_frames(data, format, args.frames, args.stride, args.scale, **options)


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    """``--preset``, ``--config FILE`` and ``--set KEY=VALUE``, the inputs of ``config.resolve``."""
    parser.add_argument("--preset", default="sparse", choices=PRESETS, help="method preset (default sparse)")
    parser.add_argument("--config", default=None, help="YAML/JSON file of config overrides")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override one config value, e.g. --set keyframes.iterations=40 (repeatable)")


def parse_intrinsics(text: str, size: str) -> Intrinsics:
    """``--intrinsics fx,fy,cx,cy`` and ``--size WIDTHxHEIGHT`` as checked intrinsics."""
    try:
        fx, fy, cx, cy = (float(v) for v in text.split(","))
        width, height = (int(v) for v in size.lower().split("x"))
    except ValueError as error:
        raise ValueError("--intrinsics must be fx,fy,cx,cy and --size WIDTHxHEIGHT") from error
    intrinsics = Intrinsics(fx, fy, cx, cy, width, height)
    intrinsics.validate()
    return intrinsics
