"""The paper's three ablation tables (section 4) on one sequence, our rows beside the paper's.

Each row is one mapping run with one switch off the paper's method (docs/architecture.md,
"Ablation switches"); the paper's method itself is run once and shared by the three tables:

  allocation  map densification   octree.allocation = projection (SplaTAM) | unique | octree (ours)
  refinement  progressive growth  refine.growth     = none | error (Scaffold-GS) | anchor (ours)
  window      keyframe window     keyframes.window  = random | overlap | coverage | dynamic (ours)

As bench/heldout_sweep.py does, frames are decoded and resized before the clock starts, so
processing FPS is the mapping loop alone (it includes the projection strategy's extra render per
frame). Each map is then scored on the held-out frames (index % 10 == 5) and on the streamed ones:
PSNR, SSIM, LPIPS (AlexNet v0.1 when its weights file exists, else "n/a"), with the snapshot size
and the anchor count. With --seeds N every row runs with seeds 0..N-1 and the tables show means
(and the spread). Writes DIR/ablations.md (the three tables) and DIR/results.json (every run).

The paper's numbers are from its Replica / ScanNet experiments at full resolution (its refinement
and window rows equal its dense version's main results); compare the ordering of rows, not values.

    .venv/bin/python bench/ablations.py                      # 7-Scenes 0:300 at 320x240, sparse
    .venv/bin/python bench/ablations.py --only window --seeds 3
    .venv/bin/python bench/ablations.py --frames 0:20 --scale 0.25 --out /tmp/ablations   # smoke test
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import ogmapping  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its thread pool)

# isort: split
import torch
from tqdm import tqdm

from ogmapping.config import resolve
from ogmapping.datasets import open_dataset
from ogmapping.frames.preprocess import resize_frame
from ogmapping.frames.selection import select
from ogmapping.mapper import Mapper
from ogmapping.quality.evaluation import ground_truth, mapper_render, score
from ogmapping.quality.metrics import Lpips, summarise
from ogmapping.runtime.profile import resolve_device


@dataclass(frozen=True)
class Row:
    name: str
    overrides: tuple[tuple[str, str], ...]  # () is the paper's method
    paper: tuple[str, ...]  # the paper's values as its .tex prints them, in the table's paper columns


@dataclass(frozen=True)
class Table:
    key: str
    title: str
    paper_columns: tuple[str, ...]
    rows: tuple[Row, ...]


TABLES = (
    Table("allocation", "Map densification (paper Tab. anchor_manage: Replica room0)",
          ("PSNR", "FPS", "size MB"), (
              Row("Projection-based (SplaTAM)", (("octree.allocation", "projection"),), ("36.18", "2.95", "71.8")),
              Row("Naive Unique", (("octree.allocation", "unique"),), ("36.24", "3.37", "39.9")),
              Row("Octree-based (ours)", (), ("36.24", "5.16", "39.9")),
          )),
    Table("refinement", "Progressive map refinement (paper Tab. growing_ablation: Replica / ScanNet, dense)",
          ("Replica PSNR", "Replica MB", "ScanNet PSNR", "ScanNet MB"), (
              Row("w/o Growing", (("refine.growth", "none"),), ("36.85", "29.4", "24.89", "19.9")),
              Row("Error-based (Scaffold-GS)", (("refine.growth", "error"),), ("38.54", "40.5", "25.27", "78.4")),
              Row("Anchor-based (ours)", (), ("38.56", "34.6", "25.61", "36.1")),
          )),
    Table("window", "Keyframe window (paper Tab. keyframe_performance_comparison: Replica, dense)",
          ("PSNR", "SSIM", "LPIPS"), (
              Row("Fixed: Random (ESLAM)", (("keyframes.window", "random"),), ("37.14", "0.969", "0.057")),
              Row("Fixed: Overlap (SplaTAM, MonoGS)", (("keyframes.window", "overlap"),), ("35.85", "0.963", "0.063")),
              Row("Fixed: Coverage-Maximizing (H2-Mapping)", (("keyframes.window", "coverage"),),
                  ("37.75", "0.972", "0.050")),
              Row("Dynamic (ours)", (), ("38.56", "0.976", "0.048")),
          )),
)

# Our columns: (label, key in a run's record, digits).
OURS = (("held-out PSNR", "heldout.psnr", 2), ("SSIM", "heldout.ssim", 3), ("LPIPS", "heldout.lpips", 3),
        ("streamed PSNR", "streamed.psnr", 2), ("FPS", "processing_fps", 2), ("size MB", "snapshot_mb", 2),
        ("anchors", "anchors", 0))


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default="../shared/data/7scenes-redkitchen", help="dataset folder (any format "
                        "ogmap run reads; default: %(default)s)")
    parser.add_argument("--frames", default="0:300", help="START:END of the sequence (default %(default)s)")
    parser.add_argument("--scale", type=float, default=0.5, help="image scale (default %(default)s: 320x240 on "
                        "7-Scenes)")
    parser.add_argument("--preset", default="sparse", help="config preset the rows start from (default %(default)s)")
    parser.add_argument("--seeds", type=int, default=1, help="runs per row, seeds 0..N-1 (default %(default)s)")
    parser.add_argument("--only", action="append", choices=[table.key for table in TABLES],
                        help="run only this table (repeatable; default: all three)")
    parser.add_argument("--device", default="auto", help="cpu, cuda or auto (default %(default)s)")
    parser.add_argument("--out", type=Path, default=Path("runs/ablations"), help="output folder for ablations.md "
                        "and results.json (default %(default)s)")
    args = parser.parse_args()
    if args.seeds < 1:
        parser.error("--seeds must be >= 1")
    return args


def map_and_score(config, device, streamed, heldout, lpips: Lpips) -> dict[str, Any]:
    """One mapping run over pre-decoded frames, scored on held-out and streamed views."""
    mapper = Mapper(config, device)
    start = time.perf_counter()
    for frame in streamed:
        mapper.process(frame)
    seconds = time.perf_counter() - start
    record: dict[str, Any] = {}
    render = mapper_render(mapper)
    for split, frames in (("heldout", heldout), ("streamed", streamed)):
        per_frame = []
        for frame in frames:
            truth = ground_truth(frame, config)
            rendered = render(truth.c2w, truth.color_intrinsics, truth)
            per_frame.append({**score(rendered, truth), "lpips": lpips(rendered.color, truth.rgb)})
        record[split] = summarise(per_frame)
    stats = mapper.stats()
    cells = torch.stack([mapper.model.anchors.codes, mapper.model.anchors.levels])
    return {
        **record,
        "processing_fps": len(streamed) / seconds,
        "mapping_seconds": seconds,
        "snapshot_mb": len(mapper.snapshot()) / 1e6,
        "anchors": stats.anchors,
        "anchors_per_level": stats.anchors_per_level,
        "duplicate_anchors": stats.anchors - int(torch.unique(cells, dim=1).shape[1]),  # projection's
        "keyframes": stats.keyframes,
        "iterations": stats.iterations,
    }


def value(record: dict[str, Any], key: str) -> float | None:
    for part in key.split("."):
        record = record.get(part) if isinstance(record, dict) else None
    return record


def cell(values: list[float | None], digits: int) -> str:
    kept = [v for v in values if v is not None]
    if not kept:
        return "n/a"
    mean = statistics.fmean(kept)
    text = f"{mean:.{digits}f}"
    if len(kept) > 1:
        text += f" ± {statistics.stdev(kept):.{digits}f}"
    return text


def markdown(tables: list[Table], runs: dict[tuple, list[dict]], header: str) -> str:
    lines = [header, ""]
    for table in tables:
        columns = ["method", *(f"paper {c}" for c in table.paper_columns), *(label for label, _, _ in OURS)]
        lines += [f"### {table.title}", "", "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
        for row in table.rows:
            paper = list(row.paper)
            ours = [cell([value(r, key) for r in runs[row.overrides]], digits) for _, key, digits in OURS]
            lines.append("| " + " | ".join([row.name, *paper, *ours]) + " |")
        lines.append("")
    return "\n".join(lines)


def main() -> None:
    args = parse_args()
    tables = [table for table in TABLES if not args.only or table.key in args.only]
    settings = list(dict.fromkeys(row.overrides for table in tables for row in table.rows))  # paper's once
    device = resolve_device(args.device)
    source = open_dataset(args.data)
    selection = select(len(source), args.frames, 1)
    streamed = [resize_frame(source[i], args.scale) for i in selection.streamed]
    heldout = [resize_frame(source[i], args.scale) for i in selection.heldout]
    lpips = Lpips(device)
    if not lpips.available:
        tqdm.write(f"LPIPS: n/a ({lpips.reason})")
    runs: dict[tuple, list[dict]] = {overrides: [] for overrides in settings}
    records = []
    progress = tqdm(total=len(settings) * args.seeds, desc="ablation runs", unit="run")
    for seed in range(args.seeds):
        for overrides in settings:
            label = " ".join(f"{k}={v}" for k, v in overrides) or "paper's method"
            progress.set_postfix_str(f"seed {seed}: {label}")
            config = resolve(args.preset, overrides={**dict(overrides), "seed": seed})
            record = map_and_score(config, device, streamed, heldout, lpips)
            runs[overrides].append(record)
            records.append({"overrides": dict(overrides), "seed": seed, **record})
            progress.update()
    progress.close()

    sample = streamed[0].color_intrinsics
    header = (f"## Ablations: {args.data} frames {args.frames} at {sample.width}x{sample.height}, preset "
              f"{args.preset}, {args.seeds} seed(s), {device}\n\n"
              f"{len(streamed)} streamed / {len(heldout)} held-out frames. Ours: held-out PSNR / SSIM / LPIPS, "
              "streamed PSNR, processing FPS (mapping loop, frames pre-decoded), snapshot size, anchors"
              f"{'' if args.seeds == 1 else '; mean ± standard deviation over seeds'}. LPIPS: "
              f"{'AlexNet v0.1' if lpips.available else 'n/a (' + lpips.reason + ')'}. The paper's columns are "
              "its own runs on Replica / ScanNet at full resolution (its refinement and window rows are its "
              "dense version): compare orderings, not values.")
    text = markdown(tables, runs, header)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "ablations.md").write_text(text + "\n")
    results = {
        "data": args.data, "frames": args.frames, "scale": args.scale, "preset": args.preset, "seeds": args.seeds,
        "device": str(device), "resolution": [sample.width, sample.height],
        "streamed_frames": len(streamed), "heldout_frames": len(heldout),
        "lpips": "AlexNet v0.1" if lpips.available else f"n/a: {lpips.reason}",
        "tables": {table.key: [{"method": row.name, "overrides": dict(row.overrides),
                                "paper": {c: float(v) for c, v in zip(table.paper_columns, row.paper, strict=True)}}
                               for row in table.rows] for table in tables},
        "runs": records,
    }
    (args.out / "results.json").write_text(json.dumps(results, indent=2))
    print(text)


if __name__ == "__main__":
    main()
