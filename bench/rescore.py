"""Score a stored map again with today's metrics, without mapping again.

``ogmap run`` scores a map once, with the metrics of its day; mapping again at the paper's resolution
costs the CPU minutes a map, rendering seconds. So when a metric joins (MS-SSIM, the paper's "SSIM") the
maps already made are scored from their ``map.safetensors``: the snapshot holds what the run rendered (the map's
average where it keeps one), and this renders every streamed and held-out view of the same frames at
the same poses. The figures this prints for PSNR, SSIM and LPIPS match the run's own results.json (a
check it prints), so a new metric stands beside figures of the same map.

    python bench/rescore.py runs/replica-dense --data ../shared/data/replica-room0/data --format replica \
        --frames 0:20 --scale 1 [--out rescored.json]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ogmapping.mapper import Mapper
from ogmapping.quality.evaluation import evaluate_views, mapper_render, open_frames
from ogmapping.quality.metrics import METRIC_KEYS

SPLITS = ("streamed", "heldout")


def rescore(run: Path, data: str, format: str, frames: str | None, scale: float, progress: bool) -> dict:
    """Each split's summary of the map in ``run``, with the figures its results.json recorded beside it."""
    mapper = Mapper.restore((run / "map.safetensors").read_bytes())
    selected = open_frames(data, format, frames, 1, scale)
    evaluation = evaluate_views(selected, mapper.config, mapper_render(mapper), None, progress, mapper.device)
    recorded_file = run / "results.json"
    recorded = json.loads(recorded_file.read_text()) if recorded_file.is_file() else {}
    return {
        "run": str(run),
        "lpips": evaluation.lpips,
        **{split: evaluation.splits[split] for split in SPLITS},
        "recorded": {split: {key: recorded.get(split, {}).get(key) for key in METRIC_KEYS} for split in SPLITS},
    }


def line(result: dict) -> str:
    """One line a run: every metric streamed / held-out, and what results.json held."""
    def both(key: str, source: dict) -> str:
        values = [source[split].get(key) for split in SPLITS]
        return " / ".join("n/a" if value is None else f"{value:.4f}" for value in values)

    now = "  ".join(f"{key} {both(key, result)}" for key in METRIC_KEYS)
    then = "  ".join(f"{key} {both(key, result['recorded'])}" for key in ("psnr", "ssim", "lpips"))
    return f"{result['run']}: {now}\n    recorded: {then}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", type=Path, help="ogmap run --out folders (map.safetensors, results.json)")
    parser.add_argument("--data", required=True, help="the dataset the runs mapped")
    parser.add_argument("--format", default="auto", help="dataset layout, as ogmap run's (default: detect)")
    parser.add_argument("--frames", default=None, help="START:END, as the runs were given")
    parser.add_argument("--scale", type=float, default=1.0, help="image scale, as the runs were given")
    parser.add_argument("--out", type=Path, help="write every run's figures here as JSON")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    args = parser.parse_args(argv)
    missing = [str(run) for run in args.runs if not (run / "map.safetensors").is_file()]
    if missing:
        parser.error(f"no map.safetensors in {', '.join(missing)}")
    results = []
    for run in args.runs:
        result = rescore(run, args.data, args.format, args.frames, args.scale, not args.quiet)
        print(line(result), flush=True)
        results.append(result)
    if args.out is not None:
        args.out.write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
