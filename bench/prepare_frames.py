"""Time a frame's depth registration and clipping: numpy (``frames.preprocess``) against torch
(``frames.preprocess_device``) on the CPU, or on CUDA with ``--device cuda`` (CUDA events).

Three cases from a 7-Scenes frame at 640x480: the dataset's cameras (a baseline along x, other intrinsics:
no footprints), the depth under a colour camera twice as dense (footprints; a reach of 2 on torch's grid),
and the dataset's cameras with a small rotation added (a transform that changes depth: torch's grid as wide
as the footprint cap). Each figure is the median of ``--repeats`` runs after one to warm up, the two
interleaved; each case first checks that the two depths are equal.

    .venv/bin/python bench/prepare_frames.py --data ../shared/data/7scenes-redkitchen --threads 1
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
from collections.abc import Callable

import ogmapping  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its thread pool)

# isort: split
import numpy as np
import torch

from ogmapping.datasets.sevenscenes import SevenScenes
from ogmapping.frames import preprocess
from ogmapping.frames.frame import Frame
from ogmapping.frames.preprocess_device import prepare_depth
from ogmapping.frames.rotation import axis_angle_matrix

DEPTH_MIN, DEPTH_MAX = 0.1, 5.0


def cases(frame: Frame) -> dict[str, Frame]:
    rotated = frame.depth_to_color.copy()
    rotated[:3, :3] = axis_angle_matrix(np.array([0.0, 1.0, 0.0]), 0.02)
    denser = frame.depth_intrinsics.scaled(2.0)
    return {
        "7-Scenes cameras": frame,
        "colour twice as dense": dataclasses.replace(frame, color_intrinsics=denser, depth_to_color=None,
                                                     rgb=np.zeros((denser.height, denser.width, 3), np.float32)),
        "7-Scenes cameras, rotated 0.02 rad": dataclasses.replace(frame, depth_to_color=rotated),
    }


def seconds(run: Callable[[], object], device: torch.device) -> float:
    if device.type != "cuda":
        start = time.perf_counter()
        run()
        return time.perf_counter() - start
    begin, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    begin.record()
    run()
    end.record()
    end.synchronize()
    return begin.elapsed_time(end) / 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", required=True, help="7-Scenes RedKitchen")
    parser.add_argument("--frame", type=int, default=0)
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    parser.add_argument("--device", default="cpu")
    options = parser.parse_args()
    if options.threads:
        torch.set_num_threads(options.threads)
    device = torch.device(options.device)
    print(f"torch threads {torch.get_num_threads()}, device {device}")
    for name, frame in cases(SevenScenes(options.data)[options.frame]).items():
        depth = torch.as_tensor(frame.depth, device=device)

        def on_torch(frame: Frame = frame, depth: torch.Tensor = depth) -> torch.Tensor:
            return prepare_depth(depth, frame, DEPTH_MIN, DEPTH_MAX)

        def on_numpy(frame: Frame = frame) -> np.ndarray:
            return preprocess.prepare(frame, DEPTH_MIN, DEPTH_MAX).depth

        if not np.array_equal(on_torch().cpu().numpy(), on_numpy()):
            raise SystemExit(f"{name}: torch's depth differs from numpy's")
        numpy_s, torch_s = [], []
        for _ in range(options.repeats):
            numpy_s.append(seconds(on_numpy, torch.device("cpu")))
            torch_s.append(seconds(on_torch, device))
        print(f"{name}: numpy {1e3 * statistics.median(numpy_s):.1f} ms, torch {1e3 * statistics.median(torch_s):.1f}"
              f" ms (fastest {1e3 * min(numpy_s):.1f} / {1e3 * min(torch_s):.1f} ms)")


if __name__ == "__main__":
    main()
