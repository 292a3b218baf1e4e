"""``ogmap``: map a dataset (``run``), write its poses (``trajectory``), render a snapshot (``render``), export
Gaussians (``export``)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from ogmapping.cli.options import add_config_arguments, add_dataset_arguments, dataset_source, parse_intrinsics
from ogmapping.cli.show_config import add_config_command
from ogmapping.cli.trajectory import command_trajectory
from ogmapping.config import parse_override_args, resolve
from ogmapping.frames.camera import validate_pose

EPILOG = """examples:
  ogmap run --data ../shared/data/7scenes-redkitchen --frames 0:100 --scale 0.25 --out runs/kitchen
  ogmap run --data ../shared/data/replica-room0 --scale 0.25 --out runs/replica
  ogmap run --data synthetic --format synthetic --preset sparse-fast --out runs/synthetic
  ogmap run --bag recording.bag --scale 0.5 --out runs/robot     # ROS 1 or 2 bag, see docs/robots.md
  ogmap trajectory --data synthetic --format synthetic --frames 0:20 --out exact.tum
  ogmap trajectory --data synthetic --format synthetic --frames 0:20 --noise-translation 0.01 \
      --noise-rotation 0.5 --noise-seed 1 --out noisy.tum
  ogmap run --data synthetic --format synthetic --frames 0:20 --poses noisy.tum --eval-poses exact.tum
  ogmap config --preset sparse --resolution 1200x680     # what the preset resolves to at that size
  ogmap render --snapshot runs/kitchen/map.safetensors --pose pose.txt --intrinsics 146,146,80,60 \\
      --size 160x120 --out renders/
"""


def optional_path(text: str | None) -> Path | None:
    return Path(text) if text else None


def command_run(args: argparse.Namespace) -> int:
    from ogmapping.cli.runner import RunOptions, run

    config = resolve(args.preset, args.config, parse_override_args(args.overrides))
    data, format, dataset_options = dataset_source(args)
    options = RunOptions(data=data, format=format, frames=args.frames, stride=args.stride,
                         scale=args.scale, preset=args.preset, device=args.device, out=Path(args.out),
                         dataset_options=dataset_options, progress=not args.quiet,
                         poses=optional_path(args.poses), eval_poses=optional_path(args.eval_poses))
    results = run(options, config)
    summary = {key: results[key] for key in ("streamed", "heldout", "at_eval_poses", "processing_fps",
                                             "snapshot_bytes", "anchors", "gaussians", "device", "resolution")
               if key in results}
    print(json.dumps(summary, indent=2))
    print(f"wrote {Path(args.out) / 'results.json'}, previews and map.safetensors")
    return 0


def command_render(args: argparse.Namespace) -> int:
    from ogmapping.mapper import Mapper

    mapper = Mapper.restore(Path(args.snapshot).read_bytes(), args.device)
    pose = validate_pose(np.loadtxt(args.pose).reshape(4, 4), "--pose")
    keyframe = mapper.nearest_keyframe(args.frame) if args.frame is not None else None
    rendered = mapper.render(pose, parse_intrinsics(args.intrinsics, args.size), keyframe)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    color = cv2.cvtColor((rendered.color * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR)
    cv2.imwrite(str(out / "color.png"), color)
    cv2.imwrite(str(out / "depth.png"), np.clip(rendered.depth * 1000, 0, 65535).astype(np.uint16))
    print(f"wrote {out / 'color.png'} and {out / 'depth.png'} (16-bit, millimetres)")
    return 0


def parse_center(text: str) -> np.ndarray:
    try:
        center = np.array([float(v) for v in text.split(",")], dtype=np.float64)
    except ValueError as error:
        raise ValueError(f"--center must be X,Y,Z in metres, got {text!r}") from error
    if center.shape != (3,) or not np.isfinite(center).all():
        raise ValueError(f"--center must be three finite numbers X,Y,Z, got {text!r}")
    return center


def command_export(args: argparse.Namespace) -> int:
    from ogmapping.mapper import Mapper
    from ogmapping.persist.export import Viewpoint, default_viewpoint, export_ply
    from ogmapping.persist.spz import write_spz

    format = export_format(args.format, args.out)
    mapper = Mapper.restore(Path(args.snapshot).read_bytes(), "cpu")
    if args.center:
        viewpoint = Viewpoint(parse_center(args.center), "--center")
    elif args.pose:
        pose = validate_pose(np.loadtxt(args.pose).reshape(4, 4), "--pose")
        viewpoint = Viewpoint(pose[:3, 3], f"the camera centre of {args.pose}")
    else:
        viewpoint = default_viewpoint(mapper)
    if format == "spz":
        count = write_spz(mapper.decode_at(viewpoint.center), args.out)
    else:
        count = export_ply(mapper, args.out, viewpoint.center)
    x, y, z = viewpoint.center
    print(f"wrote {count} Gaussians to {args.out} ({format}); view-dependent colour baked at ({x:.3f}, {y:.3f}, "
          f"{z:.3f}), {viewpoint.origin}")
    return 0


def export_format(format: str, out: str) -> str:
    """``--format``, or with auto the one ``--out``'s suffix names (.ply unless .spz)."""
    return format if format != "auto" else "spz" if Path(out).suffix.lower() == ".spz" else "ply"


def parser() -> argparse.ArgumentParser:
    root = argparse.ArgumentParser(prog="ogmap", description="OG-Mapping engine: online RGB-D mapping with "
                                   "octree-managed structured 3D Gaussians.", epilog=EPILOG,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = root.add_subparsers(dest="command", required=True)
    run = commands.add_parser("run", help="map a dataset and score it on streamed and held-out views",
                              description="Streams the selected frames (holding out every position with "
                              "index % 10 == 5 as novel views), then writes results.json, preview PNGs "
                              "(render | truth, depth below) and map.safetensors into --out.")
    add_dataset_arguments(run)
    add_config_arguments(run)
    run.add_argument("--device", default="auto", help="auto, cpu or cuda[:N] (default auto)")
    run.add_argument("--out", default="runs/latest", help="output folder (default runs/latest)")
    run.add_argument("--quiet", action="store_true", help="no progress bars")
    poses = run.add_argument_group(
        "poses", "TUM trajectory files ('timestamp tx ty tz qx qy qz qw', camera-to-world, OpenCV camera axes; "
        "`ogmap trajectory` writes them). A frame's key in them is its timestamp (matched within 0.1 ms), or its "
        "index in the source where the data gives none; a selected frame without a pose is an error before "
        "mapping starts.")
    poses.add_argument("--poses", metavar="FILE", help="map with these poses instead of the data's, e.g. odometry; "
                       "views are then judged at them too")
    poses.add_argument("--eval-poses", metavar="FILE",
                       help="also judge every view at this (exact) trajectory's pose: results.json 'at_eval_poses', "
                       "previews at_eval_poses_*.png")
    run.set_defaults(handler=command_run)
    trajectory = commands.add_parser(
        "trajectory", help="write a dataset's poses as a TUM trajectory, optionally moved by seeded noise",
        description="Writes the poses of the frames `ogmap run` streams and holds out with the same --data, "
        "--frames and --stride (--scale does not change poses) as a TUM trajectory: 'timestamp tx ty tz qx qy qz "
        "qw' a line, camera-to-world with OpenCV camera axes; a frame's key is its timestamp, else its index in "
        "the source. With --noise-translation or --noise-rotation every pose but the first is moved by seeded "
        "Gaussian noise: odometry-like input for `ogmap run --poses`, to judge against the exact trajectory "
        "with --eval-poses.")
    add_dataset_arguments(trajectory)
    trajectory.add_argument("--noise-translation", type=float, default=0.0, metavar="METRES",
                            help="standard deviation of each camera centre's noise per world axis (default 0)")
    trajectory.add_argument("--noise-rotation", type=float, default=0.0, metavar="DEGREES",
                            help="standard deviation of the angle each camera turns about its centre, about a "
                            "uniformly random axis (default 0)")
    trajectory.add_argument("--noise-seed", type=int, default=0, metavar="N", help="seed of the noise (default 0)")
    trajectory.add_argument("--out", required=True, metavar="FILE", help="the TUM file to write")
    trajectory.add_argument("--quiet", action="store_true", help="no progress bar")
    trajectory.set_defaults(handler=command_trajectory)
    render = commands.add_parser("render", help="render a snapshot from a pose")
    render.add_argument("--snapshot", required=True, help="map.safetensors written by ogmap run")
    render.add_argument("--pose", required=True, help="text file with a 4x4 camera-to-world matrix")
    render.add_argument("--intrinsics", required=True, help="fx,fy,cx,cy in pixels")
    render.add_argument("--size", required=True, help="WIDTHxHEIGHT")
    render.add_argument("--frame", type=int, metavar="INDEX",
                        help="the pose is the client's at this frame index: moved as refinement (poses.refine) moved "
                        "the keyframe nearest it, as the snapshot records (default: the pose is in the map's frame)")
    render.add_argument("--device", default="cpu")
    render.add_argument("--out", default="renders", help="output folder for color.png and depth.png")
    render.set_defaults(handler=command_render)
    export = commands.add_parser(
        "export", help="export a snapshot's Gaussians as a 3DGS .ply or a compressed .spz",
        description="Write the map's Gaussians as a standard 3DGS .ply (SH degree 0), or as Niantic's compressed "
        "SPZ (--format spz, about a quarter of the size; Spark and SuperSplat read it; needs the 'spz' extra, "
        "gsply), in SPZ's own right-up-back axes as Niantic's converter writes a .ply's. The map's colours and "
        "opacities depend on the viewpoint, a .ply holds one colour per Gaussian: the export fixes them as seen "
        "from ONE point, by default the centroid of the camera positions the map was built from. Renders of the "
        ".ply agree best with the map's own renders near that point; choose another with --center or --pose.",
    )
    export.add_argument("--snapshot", required=True, help="map.safetensors written by ogmap run or ogclient snapshot")
    export.add_argument("--out", required=True, help="path of the .ply or .spz to write")
    export.add_argument("--format", choices=("auto", "ply", "spz"), default="auto",
                        help="file format (default auto: spz for an --out ending in .spz, else ply)")
    viewpoint = export.add_mutually_exclusive_group()
    viewpoint.add_argument("--center", metavar="X,Y,Z", help="bake view-dependent colour as seen from this world point")
    viewpoint.add_argument("--pose", metavar="FILE",
                           help="bake it as seen from this camera (text file, 4x4 camera-to-world matrix)")
    export.set_defaults(handler=command_export)
    add_config_command(commands)
    return root


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        return args.handler(args)
    except (ValueError, FileNotFoundError) as error:
        print(f"ogmap: error: {error}", file=sys.stderr)
        return 2
