"""Pose corrections per frame from `ogmap run --set poses.refine=true` results, as an SVG plot and a
summary: the mean correction inside a marked stretch of frames against outside it.

Usage: python bench/poses/corrections.py RESULTS.json [RESULTS.json ...] --mark 225:275 --out corrections.svg
Each results file is one line of the plot (its folder's name labels it).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

WIDTH, HEIGHT, MARGIN = 900, 320, 50
COLOURS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b")


def series(path: Path) -> tuple[str, list[int], list[float]]:
    """(label, frame indices, correction in cm) of one run."""
    refinement = json.loads(path.read_text()).get("pose_refinement")
    if refinement is None:
        raise SystemExit(f"{path}: no pose_refinement (was the run made with --set poses.refine=true?)")
    per_frame = refinement["per_frame"]
    return path.parent.name, per_frame["index"], per_frame["correction_cm"]


def svg(lines: list[tuple[str, list[int], list[float]]], mark: tuple[int, int] | None) -> str:
    first = min(min(indices) for _, indices, _ in lines)
    last = max(max(indices) for _, indices, _ in lines)
    top = max(max(values) for _, _, values in lines) or 1.0

    def x(index: float) -> float:
        return MARGIN + (index - first) / max(last - first, 1) * (WIDTH - 2 * MARGIN)

    def y(value: float) -> float:
        return HEIGHT - MARGIN - value / top * (HEIGHT - 2 * MARGIN)

    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{WIDTH}" height="{HEIGHT}" font-family="sans-serif" '
             'font-size="12">', f'<rect width="{WIDTH}" height="{HEIGHT}" fill="white"/>']
    if mark is not None:
        parts.append(f'<rect x="{x(mark[0]):.1f}" y="{MARGIN}" width="{x(mark[1]) - x(mark[0]):.1f}" '
                     f'height="{HEIGHT - 2 * MARGIN}" fill="#eeeeee"/>')
        parts.append(f'<text x="{x(mark[0]) + 4:.1f}" y="{MARGIN + 14}">frames {mark[0]}-{mark[1]}</text>')
    parts.append(f'<line x1="{MARGIN}" y1="{y(0)}" x2="{WIDTH - MARGIN}" y2="{y(0)}" stroke="black"/>')
    parts.append(f'<line x1="{MARGIN}" y1="{MARGIN}" x2="{MARGIN}" y2="{y(0)}" stroke="black"/>')
    parts.append(f'<text x="{MARGIN}" y="{MARGIN - 8}">correction (cm), max {top:.2f}</text>')
    parts.append(f'<text x="{WIDTH - MARGIN - 40}" y="{HEIGHT - MARGIN + 30}">frame</text>')
    for tick in range(first, last + 1, max(1, (last - first) // 6)):
        parts.append(f'<text x="{x(tick) - 10:.1f}" y="{HEIGHT - MARGIN + 16}">{tick}</text>')
    for number, (label, indices, values) in enumerate(lines):
        colour = COLOURS[number % len(COLOURS)]
        points = " ".join(f"{x(i):.1f},{y(v):.1f}" for i, v in zip(indices, values, strict=True))
        parts.append(f'<polyline points="{points}" fill="none" stroke="{colour}" stroke-width="1.2"/>')
        label_y = MARGIN + 16 * (number + 1)
        parts.append(f'<text x="{WIDTH - MARGIN - 200}" y="{label_y}" fill="{colour}">{label}</text>')
    parts.append("</svg>")
    return "\n".join(parts) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("results", nargs="+", type=Path, help="results.json of refining runs")
    parser.add_argument("--mark", metavar="A:B", help="a stretch of frames to shade and summarise apart")
    parser.add_argument("--out", type=Path, default=Path("corrections.svg"), help="the SVG to write")
    args = parser.parse_args()
    mark = tuple(int(part) for part in args.mark.split(":")) if args.mark else None
    lines = [series(path) for path in args.results]
    args.out.write_text(svg(lines, mark))
    for label, indices, values in lines:
        summary = f"{label}: mean correction {sum(values) / len(values):.2f} cm over {len(values)} frames"
        if mark is not None:
            inside = [v for i, v in zip(indices, values, strict=True) if mark[0] <= i <= mark[1]]
            outside = [v for i, v in zip(indices, values, strict=True) if not mark[0] <= i <= mark[1]]
            if inside and outside:
                summary += (f"; frames {mark[0]}-{mark[1]}: {sum(inside) / len(inside):.2f} cm, "
                            f"the others: {sum(outside) / len(outside):.2f} cm")
        print(summary)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
