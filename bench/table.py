"""One Markdown table from ``ogmap run`` results.json files (folders or files as arguments)."""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

HEADER = ("run", "preset", "resolution", "streamed/held-out frames", "processing FPS", "render FPS",
          "PSNR streamed / held-out", "PSNR affine-fit streamed / held-out", "SSIM streamed / held-out",
          "MS-SSIM streamed / held-out", "LPIPS streamed / held-out",
          "depth L1 cm streamed / held-out", "keyframes / iterations", "anchors (per level)", "snapshot KB",
          "peak RSS MB")


def load(path: str) -> dict[str, Any]:
    file = Path(path)
    return json.loads((file / "results.json" if file.is_dir() else file).read_text())


def pair(result: dict[str, Any], key: str, digits: int) -> str:
    values = [result[split].get(key) for split in ("streamed", "heldout")]  # None: a file older than the key
    return " / ".join("n/a" if value is None else f"{value:.{digits}f}" for value in values)


def row(name: str, r: dict[str, Any]) -> list[str]:
    return [
        name, r["preset"], "x".join(map(str, r["resolution"])),
        f"{r['streamed']['frames']} / {r['heldout']['frames']}",
        f"{r['processing_fps']:.2f}", f"{r['render_fps']:.1f}",
        pair(r, "psnr", 2), pair(r, "psnr_affine", 2), pair(r, "ssim", 3), pair(r, "ms_ssim", 3), pair(r, "lpips", 3),
        pair(r, "depth_l1_cm", 2),
        f"{r['keyframes']} / {r.get('iterations', 'n/a')}",
        f"{r['anchors']} ({', '.join(map(str, r['anchors_per_level']))})",
        f"{r['snapshot_bytes'] / 1024:.0f}", f"{r['peak_rss_bytes'] / 2**20:.0f}",
    ]


def main(paths: list[str]) -> int:
    if not paths:
        print(__doc__)
        return 2
    print("| " + " | ".join(HEADER) + " |")
    print("|" + "---|" * len(HEADER))
    for path in paths:
        print("| " + " | ".join(row(Path(path).name, load(path))) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
