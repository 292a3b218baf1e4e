"""One Markdown table from ``ogmap run`` results.json files, beside the paper's Replica speeds.

Usage: ``python bench/gpu/table.py OUT/dense OUT/sparse OUT/sparse-fast`` (folders or results.json).
The paper's processing FPS were measured on Replica with an RTX 4090 (its Table "key performance
metrics on Replica"); they are context only, since data, resolution and GPU differ here.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

PAPER_REPLICA_FPS = {"dense": 5.6, "sparse": 8.5, "sparse-fast": 16.1}
COLUMNS = (
    "preset",
    "processing FPS",
    "paper FPS (Replica, 4090)",
    "render FPS",
    "PSNR streamed / held-out",
    "SSIM streamed / held-out",
    "LPIPS streamed / held-out",
    "depth L1 cm streamed / held-out",
    "snapshot MB",
    "peak GPU MB",
    "peak GPU MB every 100 frames",
)


def load(path: str) -> dict[str, Any]:
    file = Path(path)
    return json.loads((file / "results.json" if file.is_dir() else file).read_text())


def number(value: Any, digits: int) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def pair(result: dict[str, Any], key: str, digits: int) -> str:
    streamed = (result.get("streamed") or {}).get(key)
    heldout = (result.get("heldout") or {}).get(key)
    return f"{number(streamed, digits)} / {number(heldout, digits)}"


def megabytes(value: Any) -> str:
    return "–" if value is None else f"{value / 1e6:.1f}"


def row(result: dict[str, Any]) -> list[str]:
    preset = result.get("preset", "?")
    return [
        preset,
        number(result.get("processing_fps"), 2),
        number(PAPER_REPLICA_FPS.get(preset), 1),
        number(result.get("render_fps"), 1),
        pair(result, "psnr", 2),
        pair(result, "ssim", 3),
        pair(result, "lpips", 3),
        pair(result, "depth_l1_cm", 2),
        megabytes(result.get("snapshot_bytes")),
        megabytes(result.get("peak_gpu_memory_bytes")),
        " / ".join(megabytes(entry.get("peak_gpu_memory_bytes")) for entry in result.get("memory_per_100_frames", [])),
    ]


def setting(result: dict[str, Any]) -> str:
    """Where and on what a run was measured, so rows from different set-ups are not mixed up."""
    frames = result.get("frames") or {}
    width, height = result.get("resolution") or ("?", "?")
    return (
        f"device {result.get('device', '?')}, backend {result.get('backend', '?')}, {width}x{height}, "
        f"{frames.get('streamed', '?')} streamed + {frames.get('heldout', '?')} held-out frames"
    )


def table(results: list[dict[str, Any]]) -> str:
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(row(result)) + " |" for result in results]
    settings = dict.fromkeys(f"- {r.get('preset', '?')}: {setting(r)}" for r in results)
    return "\n".join([*lines, "", *settings, "- MB = 10^6 bytes."])


def main(paths: list[str]) -> int:
    if not paths:
        print(__doc__, file=sys.stderr)
        return 2
    print(table([load(path) for path in paths]))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
