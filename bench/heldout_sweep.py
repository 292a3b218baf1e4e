"""Map a sequence once per setting and score the held-out frames (and with --streamed the rest): a tuning loop.

What ``ogmap run`` measures, minus what tuning does not need: frames are decoded before the clock
starts (so FPS is the mapping loop alone) and only the held-out frames (index % 10 == 5) are
rendered and scored unless --streamed asks for the streamed ones too. Each setting is one line of
``--set``-style overrides; one result line each.

    .venv/bin/python bench/heldout_sweep.py --preset sparse "" "keyframes.window_scale=0.5"
    .venv/bin/python bench/heldout_sweep.py --data ../shared/data/replica-room0/data --frames 0:20 --streamed ""
"""

from __future__ import annotations

import argparse
import time

import ogmapping  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its thread pool)

# isort: split
from ogmapping.config import parse_override_args, resolve
from ogmapping.datasets import open_dataset
from ogmapping.evaluation import ground_truth, score
from ogmapping.mapper import Mapper
from ogmapping.metrics import summarise
from ogmapping.preprocess import resize_frame
from ogmapping.selection import select


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("settings", nargs="+", help='space-separated KEY=VALUE overrides per setting ("" = preset)')
    parser.add_argument("--data", default="../shared/data/7scenes-redkitchen")
    parser.add_argument("--frames", default="0:300", help="START:END (default 0:300)")
    parser.add_argument("--scale", type=float, default=0.5, help="image scale (default 0.5: 320x240)")
    parser.add_argument("--preset", default="sparse")
    parser.add_argument("--streamed", action="store_true", help="score the streamed frames as well")
    args = parser.parse_args()
    source = open_dataset(args.data)
    selection = select(len(source), args.frames, 1)
    streamed = [resize_frame(source[i], args.scale) for i in selection.streamed]
    heldout = [resize_frame(source[i], args.scale) for i in selection.heldout]
    for setting in args.settings:
        config = resolve(args.preset, overrides=parse_override_args(setting.split()))
        mapper = Mapper(config)
        start = time.perf_counter()
        keyframes = sum(mapper.process(frame).keyframe for frame in streamed)
        seconds = time.perf_counter() - start
        splits = {"held-out": heldout, "streamed": streamed} if args.streamed else {"held-out": heldout}
        scores = []
        for name, frames in splits.items():
            truths = [ground_truth(frame, config) for frame in frames]
            quality = summarise([score(mapper.render(t.c2w, t.color_intrinsics), t) for t in truths])
            scores.append(f"{name} PSNR {quality['psnr']:.2f} dB, SSIM {quality['ssim']:.3f}, "
                          f"depth L1 {quality['depth_l1_cm']:.2f} cm")
        print(f"{args.preset} [{setting}]: {len(streamed) / seconds:.2f} FPS ({seconds:.0f} s), {'; '.join(scores)}, "
              f"{keyframes} keyframes, {mapper.iterations} iterations, {len(mapper.anchors)} anchors", flush=True)


if __name__ == "__main__":
    main()
