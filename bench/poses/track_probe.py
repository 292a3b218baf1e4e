"""Where tracking takes one frame's pose: the frame, given a noisy pose, tracked alone for many steps against
the map of the frames streamed before it (mapped at their own poses, refinement on), printing its pose
error and tracking loss as it goes, and the loss at its exact pose. An exact pose whose loss is lower
than where tracking ended means tracking has not converged; a higher one, that the loss's minimum lies
off the truth (the young map's own error), which no step rule reaches.

    python bench/poses/track_probe.py --data ../shared/data/replica-room0/data --format replica \\
        --frames 0:20 --scale 0.5 --noisy noisy.tum --frame 1 [--steps 60] [--newton 4] [--set KEY=VALUE ...]

``--noisy`` is a TUM trajectory covering the frames (``ogmap trajectory --noise-translation ...``, as
``bench/poses/noisy_poses.sh`` writes it); ``--frame`` counts streamed frames from 0 (0 is the first
keyframe, which is never tracked).
"""

from __future__ import annotations

import argparse
import dataclasses

import cv2
import numpy as np
import torch

from ogmapping.config import parse_override_args, resolve
from ogmapping.frames.preprocess import prepare
from ogmapping.frames.trajectory import pose_errors, read_tum
from ogmapping.mapper import Mapper
from ogmapping.optim.pose_newton import newton_track
from ogmapping.optim.poses import PoseCorrection
from ogmapping.quality.evaluation import open_frames


def correction_to(exact: np.ndarray, given: np.ndarray, device: torch.device) -> PoseCorrection:
    """The correction that takes the ``given`` camera-to-world to the ``exact`` one."""
    correction = PoseCorrection(device)
    rotation = cv2.Rodrigues(exact[:3, :3] @ given[:3, :3].T)[0].ravel()
    with torch.no_grad():
        correction.delta.copy_(torch.as_tensor(np.concatenate([exact[:3, 3] - given[:3, 3], rotation])))
    return correction


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", required=True)
    parser.add_argument("--format", default="auto")
    parser.add_argument("--frames", default="0:20")
    parser.add_argument("--scale", type=float, default=0.5)
    parser.add_argument("--preset", default="sparse")
    parser.add_argument("--noisy", required=True, help="TUM trajectory the probed frame takes its pose from")
    parser.add_argument("--frame", type=int, default=1, help="streamed frame to track (1 or later)")
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--every", type=int, default=5, help="print every this many steps")
    parser.add_argument("--newton", type=int, default=0,
                        help="then this many Gauss-Newton steps (poses.track_newton_iterations), each printed")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    args = parser.parse_args()
    frames = open_frames(args.data, args.format, args.frames, 1, args.scale)
    streamed = list(frames.selection.streamed)
    if not 1 <= args.frame < len(streamed):
        parser.error(f"--frame must be 1 to {len(streamed) - 1}")
    config = resolve(args.preset, overrides={"poses.refine": "true", **parse_override_args(args.overrides)})
    mapper = Mapper(config, "cpu")
    for position in streamed[:args.frame]:
        mapper.process(frames.load(position))
    frame = frames.load(streamed[args.frame])
    exact = np.asarray(frame.c2w, dtype=np.float64)
    given = read_tum(args.noisy).pose_of(frame)
    noisy = prepare(dataclasses.replace(frame, c2w=given), config.octree.depth_min, config.octree.depth_max)
    loss_at = mapper.tracker.objective(noisy)
    settings = mapper.config.poses

    def error(correction: PoseCorrection) -> str:
        with torch.no_grad():
            refined = correction.refined(torch.as_tensor(given, dtype=torch.float32)).double().numpy()
        translation, rotation = pose_errors(refined[None], exact[None])
        return f"error {100 * float(translation[0]):.3f} cm {float(rotation[0]):.3f} deg"

    at_exact = correction_to(exact, given, mapper.device)
    with torch.no_grad():
        print(f"exact pose: {error(at_exact)}, loss {float(loss_at(at_exact)):.5f}")
    correction = PoseCorrection(mapper.device)
    for step in range(args.steps + 1):
        loss = loss_at(correction)
        if step % args.every == 0 or step == args.steps:
            print(f"step {step:3d}: {error(correction)}, loss {float(loss.detach()):.5f}", flush=True)
        if step < args.steps:
            (loss + correction.prior(settings)).backward()
            correction.step(settings)
    residuals_at = mapper.tracker.residuals(noisy)
    for step in range(args.newton):
        done = newton_track(residuals_at, correction, settings, 1, lambda: False)
        with torch.no_grad():
            loss = float(loss_at(correction))
        print(f"Gauss-Newton step {step + 1}: {error(correction)}, loss {loss:.5f}, {done.renders} renders", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
