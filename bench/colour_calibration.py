"""Fit the colour camera of an unregistered RGB-D sequence to its depth camera, from edges alone.

7-Scenes ships the depth camera's K and poses; its colour camera is another camera a few
centimetres away. Depth discontinuities (an object's silhouette against what lies behind it) are
also colour edges, so a calibration is scored by the mean colour-gradient magnitude at the
silhouette points of the depth images, projected into the colour images: the better the colour
camera model, the more of them land on an edge. The model is a pinhole (fx = fy, cx, cy) displaced
by ``baseline`` metres along the depth camera's x axis, found by coordinate descent with halving
steps. Poses play no part, so the fit cannot borrow from the mapper or from held-out frames.

    .venv/bin/python bench/colour_calibration.py --data ../shared/data/7scenes-redkitchen --every 6
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass, replace

import cv2
import numpy as np
from tqdm import tqdm

from ogmapping.datasets import open_dataset

SILHOUETTE_STEP = 0.1  # metres: a neighbour this much farther makes a pixel a silhouette point
BORDER = 3  # pixels dropped at each image border
DEPTH_BANDS = ((0.0, 1.3), (1.3, 2.0), (2.0, 2.6), (2.6, 10.0))


@dataclass(frozen=True)
class ColourCamera:
    """Colour camera as published numbers (integer pixel centres) and its offset from the depth camera."""

    focal: float
    cx: float
    cy: float
    baseline: float  # metres along the depth camera's x axis; the colour camera sits at +baseline

    def nudged(self, field: str, step: float) -> ColourCamera:
        return replace(self, **{field: getattr(self, field) + step})


@dataclass
class Silhouettes:
    """One frame's silhouette points in the depth camera and its colour-gradient image."""

    x: np.ndarray
    y: np.ndarray
    z: np.ndarray
    gradient: np.ndarray


def silhouettes(depth: np.ndarray, gray: np.ndarray, depth_k: tuple[float, float, float, float]) -> Silhouettes:
    """Foreground pixels next to a farther surface, back-projected; the colour image's gradient magnitude."""
    nearer = np.zeros(depth.shape, bool)
    for shift in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        neighbour = np.roll(depth, shift, (0, 1))
        nearer |= (depth > 0) & (neighbour > 0) & (neighbour - depth > SILHOUETTE_STEP)
    nearer[:BORDER] = nearer[-BORDER:] = False
    nearer[:, :BORDER] = nearer[:, -BORDER:] = False
    rows, cols = np.nonzero(nearer)
    z = depth[rows, cols]
    fx, fy, cx, cy = depth_k
    smooth = cv2.GaussianBlur(gray, (5, 5), 1.0)
    gradient = np.hypot(cv2.Sobel(smooth, cv2.CV_32F, 1, 0), cv2.Sobel(smooth, cv2.CV_32F, 0, 1))
    return Silhouettes((cols - cx) / fx * z, (rows - cy) / fy * z, z, gradient)


def edge_score(frames: list[Silhouettes], camera: ColourCamera, band: tuple[float, float] | None = None) -> float:
    """Mean colour gradient under the projected silhouette points (higher: better registered)."""
    total, count = 0.0, 0
    for frame in frames:
        keep = slice(None) if band is None else (frame.z >= band[0]) & (frame.z < band[1])
        x, y, z = frame.x[keep], frame.y[keep], frame.z[keep]
        if len(z) == 0:
            continue
        u = (camera.focal * (x - camera.baseline) / z + camera.cx).astype(np.float32)
        v = (camera.focal * y / z + camera.cy).astype(np.float32)
        values = cv2.remap(frame.gradient, u.reshape(1, -1), v.reshape(1, -1), cv2.INTER_LINEAR)
        total += float(values.sum())
        count += len(z)
    return total / max(count, 1)


def fit(frames: list[Silhouettes], start: ColourCamera, baseline: bool = True, rounds: int = 4) -> ColourCamera:
    """Coordinate descent over the parameters (the baseline too, if asked), halving the steps after each round."""
    steps = {"focal": 4.0, "cx": 1.0, "cy": 1.0} | ({"baseline": 0.005} if baseline else {})
    best, best_score = start, edge_score(frames, start)
    for _ in tqdm(range(rounds), desc="fitting", unit="round"):
        improved = True
        while improved:
            improved = False
            for field, step in steps.items():
                for sign in (1.0, -1.0):
                    candidate = best.nudged(field, sign * step)
                    candidate_score = edge_score(frames, candidate)
                    if candidate_score > best_score + 1e-6:
                        best, best_score, improved = candidate, candidate_score, True
        steps = {field: step / 2 for field, step in steps.items()}
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default="../shared/data/7scenes-redkitchen")
    parser.add_argument("--every", type=int, default=6, help="use every n-th frame (default 6: never index %% 10 == 5)")
    parser.add_argument("--start", default="528,314.5,238.5,0.025", help="focal,cx,cy,baseline to start from")
    args = parser.parse_args()
    source = open_dataset(args.data)
    depth_k = source.depth_intrinsics
    published = (depth_k.fx, depth_k.fy, depth_k.cx - 0.5, depth_k.cy - 0.5)
    frames = []
    for position in tqdm(range(0, len(source), args.every), desc="reading", unit="frame"):
        frame = source[position]
        gray = cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2GRAY)
        frames.append(silhouettes(frame.depth, gray, published))
    print(f"{sum(len(f.z) for f in frames)} silhouette points in {len(frames)} frames")
    two_d = ColourCamera(528.0, 314.5, 238.5, 0.0)
    flat = fit(frames, two_d, baseline=False)
    print(f"fitted without a baseline: focal {flat.focal:.2f} px, cx {flat.cx:.3f}, cy {flat.cy:.3f}")
    fitted = fit(frames, ColourCamera(*(float(v) for v in args.start.split(","))))
    print(f"fitted: focal {fitted.focal:.2f} px, cx {fitted.cx:.3f}, cy {fitted.cy:.3f}, "
          f"baseline {fitted.baseline * 100:.2f} cm")
    print("| depth band (m) | silhouette points | edge score: SOURCE.md's 528 / 314.5 / 238.5 | "
          "fitted without a baseline | fitted |")
    print("|---|---|---|---|---|")
    for band in (None, *DEPTH_BANDS):
        low, high = band or (0.0, np.inf)
        points = sum(int(((f.z >= low) & (f.z < high)).sum()) for f in frames)
        label = "all" if band is None else f"{low}-{high}"
        scores = " | ".join(f"{edge_score(frames, camera, band):.4f}" for camera in (two_d, flat, fitted))
        print(f"| {label} | {points} | {scores} |")


if __name__ == "__main__":
    main()
