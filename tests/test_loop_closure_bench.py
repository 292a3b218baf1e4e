"""bench/loop_closure.py on the synthetic room: the maps asked for, each scored at the exact poses, the gap to
the exact map printed only where that map was made, and a bad ``--modes`` refused before any mapping."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "bench" / "loop_closure.py"
TINY = ["--data", "synthetic", "--frames", "0:8", "--drift-frames", "4", "--scale", "0.25",
        "--preset", "sparse-fast"]


def run(*arguments: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *TINY, *arguments], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)


def test_a_subset_of_maps_is_made_and_the_gap_follows_the_exact_map():
    done = run("--modes", "corrected,exact,uncorrected")
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert "4 drifting to 0.1 m and 3 degrees" in lines[0]
    scored = {line.split()[0]: line for line in lines[1:]}
    assert list(scored) == ["corrected", "exact", "uncorrected"]
    assert "gap to exact" not in scored["corrected"]  # made before the exact map
    assert "(gap to exact +0.00 dB)" in scored["exact"]
    gap = float(re.search(r"gap to exact ([-+][0-9.]+) dB", scored["uncorrected"]).group(1))
    psnr = {mode: float(re.search(r"exact poses +([0-9.]+) dB", line).group(1)) for mode, line in scored.items()}
    assert abs(gap - (psnr["uncorrected"] - psnr["exact"])) < 0.011
    assert psnr["uncorrected"] < psnr["exact"]  # the drift kept costs quality at the exact poses


def test_unknown_modes_are_refused_by_name():
    done = run("--modes", "exact,drifted")
    assert done.returncode == 2
    assert "--modes takes a comma-separated list of exact, uncorrected, corrected (got 'exact,drifted')" in done.stderr
