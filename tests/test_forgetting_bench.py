"""bench/forgetting.py on the synthetic room: with ``--at``, the held-out frames before each named frame are scored as
the map stands then, before the run's own line; a bad ``--at`` is refused before any mapping."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "bench" / "forgetting.py"
TINY = ["--data", "synthetic", "--frames", "0:18", "--scale", "0.25", "--preset", "sparse-fast", "--stretch", "10"]


def run(*arguments: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *TINY, *arguments], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)


def test_checkpoints_score_the_heldout_frames_mapped_so_far():
    done = run("--at", "4,9,15,17", "")
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    # Frame 4 comes before the first held-out frame (5): nothing to score there. Frame 15 is held out, never
    # mapped: the map is scored once frame 16 is.
    assert [line.split(":")[0].strip() for line in lines[:-1]] == ["after frame 9", "after frame 16",
                                                                    "after frame 17"]
    after_9, after_16, after_17, final = lines
    assert re.fullmatch(r"  after frame 9: held-out PSNR raw [0-9.]+ dB, per 10 frames: [0-9.]+", after_9)
    # From frame 16 on both held-out frames (5 and 15) are before it, each in a stretch of its own.
    for line in (after_16, after_17):
        assert re.fullmatch(r"  after frame 1[67]: held-out PSNR raw [0-9.]+ dB, per 10 frames: [0-9.]+ [0-9.]+", line)
    assert final.startswith("sparse-fast []:")
    # The map after the last streamed frame is the run's map: the checkpoint and the final figures agree.
    final_stretches = re.search(r"held-out PSNR raw [0-9.]+ dB, per 10 frames: ([0-9. ]+);", final).group(1).split()
    assert after_17.split("per 10 frames: ")[1].split() == final_stretches


def test_bad_checkpoints_are_refused_by_name():
    done = run("--at", "9,x", "")
    assert done.returncode == 2
    assert "expected comma-separated frame indices, got '9,x'" in done.stderr
    done = run("--at", "9,18", "")
    assert done.returncode == 2
    assert "--at 18 is outside the streamed frames 0-17" in done.stderr
