"""What a held-out frame's error is made of: exposure, a small misalignment, blur, coverage.

Maps the streamed frames once, then for every held-out frame prints the PSNR of the render and of
four diagnostics: after the best affine colour map of the render onto the frame (exposure and white
balance), at the best whole-pixel shift within 2 px (pose or calibration offset), against the frame
blurred with a sigma-1 Gaussian (a render blurrier than the frame scores higher there), and the
share of pixels the map covers with alpha below 0.95 (a half-transparent map).

    .venv/bin/python bench/heldout_errors.py --frames 0:300 --scale 0.5
"""

from __future__ import annotations

import argparse

import ogmapping  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its thread pool)

# isort: split
import cv2
import numpy as np
from sequence import add_sequence_arguments, load_sequence

from ogmapping.config import parse_override_args, resolve
from ogmapping.mapper import Mapper
from ogmapping.quality.evaluation import ground_truth, mapper_render
from ogmapping.quality.metrics import psnr

MARGIN = 3  # pixels dropped at each border when comparing shifted renders


def affine_fit(render: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """The render through the 3x4 colour map that brings it closest to the truth (least squares)."""
    pixels = np.concatenate([render.reshape(-1, 3), np.ones((render.size // 3, 1), np.float32)], axis=1)
    matrix, *_ = np.linalg.lstsq(pixels, truth.reshape(-1, 3), rcond=None)
    return (pixels @ matrix).reshape(truth.shape)


def best_shift(render: np.ndarray, truth: np.ndarray) -> tuple[float, tuple[int, int]]:
    inner = (slice(MARGIN, -MARGIN), slice(MARGIN, -MARGIN))
    return max(
        (psnr(np.roll(render, (dy, dx), axis=(0, 1))[inner], truth[inner]), (dy, dx))
        for dy in range(-2, 3) for dx in range(-2, 3)
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_sequence_arguments(parser)
    parser.add_argument("--set", default="", help="space-separated KEY=VALUE overrides")
    args = parser.parse_args()
    sequence = load_sequence(args)
    config = resolve(args.preset, overrides=parse_override_args(args.set.split()))
    mapper = Mapper(config)
    for frame in sequence.streamed:
        mapper.process(frame)
    rows, render = [], mapper_render(mapper)
    for frame in sequence.heldout:
        truth = ground_truth(frame, config)
        rendered = render(truth.c2w, truth.color_intrinsics, truth)
        image = truth.rgb.astype(np.float32) / 255 if truth.rgb.dtype == np.uint8 else truth.rgb
        shifted, offset = best_shift(rendered.color, image)
        row = (psnr(rendered.color, image), psnr(affine_fit(rendered.color, image), image), shifted,
               psnr(rendered.color, cv2.GaussianBlur(image, (0, 0), 1.0)), float(np.mean(rendered.alpha < 0.95)))
        rows.append(row)
        print(f"frame {truth.index}: PSNR {row[0]:.2f}, affine-fitted {row[1]:.2f}, best shift {row[2]:.2f} at "
              f"{offset}, against blurred truth {row[3]:.2f}, alpha < 0.95 on {row[4]:.1%}", flush=True)
    mean = np.mean(rows, axis=0)
    print(f"mean over {len(rows)} held-out frames: PSNR {mean[0]:.2f}, affine-fitted {mean[1]:.2f}, best shift "
          f"{mean[2]:.2f}, against blurred truth {mean[3]:.2f}, alpha < 0.95 on {mean[4]:.1%}")


if __name__ == "__main__":
    main()
