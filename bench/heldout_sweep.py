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

import ogmapping  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its thread pool)

# isort: split
from sequence import add_sequence_arguments, load_sequence, map_setting

from ogmapping.quality.evaluation import ground_truth, mapper_render, score
from ogmapping.quality.metrics import summarise


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("settings", nargs="+", help='space-separated KEY=VALUE overrides per setting ("" = preset)')
    add_sequence_arguments(parser)
    parser.add_argument("--streamed", action="store_true", help="score the streamed frames as well")
    args = parser.parse_args()
    sequence = load_sequence(args)
    streamed, heldout = sequence.streamed, sequence.heldout
    for setting in args.settings:
        run = map_setting(args.preset, setting, streamed)
        config, mapper, keyframes, seconds = run.config, run.mapper, run.keyframes, run.seconds
        splits = {"held-out": heldout, "streamed": streamed} if args.streamed else {"held-out": heldout}
        scores, render = [], mapper_render(mapper)
        for name, frames in splits.items():
            truths = [ground_truth(frame, config) for frame in frames]
            quality = summarise([score(render(t.c2w, t.color_intrinsics, t), t) for t in truths])
            scores.append(f"{name} PSNR {quality['psnr']:.2f} dB, SSIM {quality['ssim']:.3f}, "
                          f"depth L1 {quality['depth_l1_cm']:.2f} cm")
        print(f"{args.preset} [{setting}]: {len(streamed) / seconds:.2f} FPS ({seconds:.0f} s), {'; '.join(scores)}, "
              f"{keyframes} keyframes, {mapper.model.iterations} iterations, {len(mapper.model.anchors)} anchors",
              flush=True)


if __name__ == "__main__":
    main()
