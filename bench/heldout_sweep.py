"""Map 7-Scenes frames once per setting and score only the held-out frames: a fast tuning loop.

What ``ogmap run`` measures, minus what tuning does not need: frames are decoded before the clock
starts (so FPS is the mapping loop alone) and only the held-out frames (index % 10 == 5) are
rendered and scored. Each setting is one line of ``--set``-style overrides; one result line each.

    .venv/bin/python bench/heldout_sweep.py --preset sparse "" "keyframes.window_scale=0.5"
"""

from __future__ import annotations

import argparse
import time

import ogmapping  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its thread pool)

# isort: split
from ogmapping.config import build, parse_override_args
from ogmapping.datasets import open_dataset
from ogmapping.mapper import Mapper
from ogmapping.metrics import summarise
from ogmapping.preprocess import resize_frame
from ogmapping.runner import ground_truth, score
from ogmapping.selection import select


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("settings", nargs="+", help='space-separated KEY=VALUE overrides per setting ("" = preset)')
    parser.add_argument("--data", default="../shared/data/7scenes-redkitchen")
    parser.add_argument("--frames", default="0:300", help="START:END (default 0:300)")
    parser.add_argument("--scale", type=float, default=0.5, help="image scale (default 0.5: 320x240)")
    parser.add_argument("--preset", default="sparse")
    args = parser.parse_args()
    source = open_dataset(args.data)
    selection = select(len(source), args.frames, 1)
    streamed = [resize_frame(source[i], args.scale) for i in selection.streamed]
    heldout = [resize_frame(source[i], args.scale) for i in selection.heldout]
    for setting in args.settings:
        config = build(args.preset, parse_override_args(setting.split()))
        mapper = Mapper(config)
        start = time.perf_counter()
        for frame in streamed:
            mapper.process(frame)
        seconds = time.perf_counter() - start
        truths = [ground_truth(frame, config) for frame in heldout]
        quality = summarise([score(mapper.render(t.c2w, t.color_intrinsics), t) for t in truths])
        print(f"{args.preset} [{setting}]: {len(streamed) / seconds:.2f} FPS ({seconds:.0f} s), held-out "
              f"PSNR {quality['psnr']:.2f} dB, SSIM {quality['ssim']:.3f}, depth L1 {quality['depth_l1_cm']:.2f} cm, "
              f"{mapper.iterations} iterations, {len(mapper.anchors)} anchors", flush=True)


if __name__ == "__main__":
    main()
