"""The mapper, end to end through ``ogmap run``, judged by image quality.

Floors are set a little below what the code measured (see bench/RESULTS.md), so a regression
fails them. They run on small inputs to keep the suite fast.
"""

import json
import subprocess
import sys

import pytest

from ogmapping.config import resolve
from ogmapping.runner import RunOptions, run

RESULT_KEYS = {"streamed", "heldout", "processing_fps", "snapshot_bytes", "anchors", "gaussians", "device",
               "preset", "resolution"}
SYNTHETIC_PSNR_FLOOR = 33.0  # measured 33.77 dB streamed (31.9 before every frame was optimised)
TSDF_HELDOUT_PSNR_0_99_160 = 18.67  # Open3D TSDF fusion of frames 0-99 at 160x120 (SOURCE.md)
# Measured 24.73 dB held-out, 24.55 streamed (seed 0). Seeds 0-2 give 23.97-25.07 held-out, mean 24.59; before the
# alpha cap moved to 0.999 and keyframes were stored compact, 23.15-25.81, mean 24.42, and seed 0 gave 25.81 against the
# old floor 24.9 (bench/RESULTS.md, "Issue 14 on the CPU"): the floor follows one trajectory, not the average.
REAL_160_PSNR_FLOOR = 24.3
REPLICA_STREAMED_PSNR_FLOOR = 31.6  # measured 32.07 dB (Intel), 31.86 (AMD); 22.39 before every frame was optimised
REPLICA_HELDOUT_PSNR_FLOOR = 31.6  # measured 32.17 dB
REPLICA_SSIM_FLOOR = 0.935  # measured 0.941
# With model.anchor_colour: measured 34.68 / 34.69 dB streamed / held-out, SSIM 0.962 (bench/RESULTS.md).
REPLICA_ANCHOR_COLOUR_PSNR_FLOOR = 34.0
REPLICA_ANCHOR_COLOUR_SSIM_FLOOR = 0.955
REAL_320_PSNR_FLOOR = 24.9  # measured 25.28 dB held-out, 25.36 streamed on frames 0-59


def test_synthetic_scene_reaches_30_db(tmp_path):
    options = RunOptions(data="synthetic", format="synthetic", frames="0:12", scale=0.25, preset="sparse",
                         out=tmp_path, progress=False)
    results = run(options, resolve("sparse"))
    assert results.keys() >= RESULT_KEYS
    assert results["streamed"]["frames"] == 11 and results["heldout"]["frames"] == 1
    assert results["streamed"]["psnr"] >= SYNTHETIC_PSNR_FLOOR
    assert results["streamed"]["depth_l1_cm"] < 3.0
    assert (tmp_path / "map.safetensors").stat().st_size == results["snapshot_bytes"]
    assert list(tmp_path.glob("streamed_*.png")) and list(tmp_path.glob("heldout_*.png"))


@pytest.mark.realdata
def test_seven_scenes_0_99_at_160x120_beats_tsdf_clearly(seven_scenes, tmp_path):
    command = [sys.executable, "-m", "ogmapping.cli", "run", "--data", str(seven_scenes), "--frames", "0:100",
               "--scale", "0.25", "--preset", "sparse", "--out", str(tmp_path), "--quiet"]
    subprocess.run(command, check=True, capture_output=True, timeout=600)
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["resolution"] == [160, 120]
    assert results["heldout"]["frames"] == 10
    assert results["heldout"]["psnr"] >= REAL_160_PSNR_FLOOR > TSDF_HELDOUT_PSNR_0_99_160 + 5
    assert results["streamed"]["psnr"] >= REAL_160_PSNR_FLOOR
    assert results["heldout"]["depth_l1_cm"] < 3.5


def run_sparse(data, frames: str, scale: float, out, overrides: dict | None = None) -> dict:
    """``ogmap run`` of the ``sparse`` preset (plus ``overrides``), in process and without progress bars."""
    options = RunOptions(data=str(data), frames=frames, scale=scale, preset="sparse", out=out, progress=False)
    return run(options, resolve("sparse", overrides=overrides or {}))


@pytest.mark.realdata
def test_seven_scenes_320x240_holds_its_quality(seven_scenes, tmp_path):
    results = run_sparse(seven_scenes, "0:60", 0.5, tmp_path)
    assert results["resolution"] == [320, 240]
    assert results["heldout"]["psnr"] >= REAL_320_PSNR_FLOOR
    assert results["streamed"]["psnr"] >= REAL_320_PSNR_FLOOR


@pytest.mark.realdata
def test_replica_room0_at_600x340_is_sharp_and_learns_from_every_frame(replica_room0, tmp_path):
    """The paper's own scene: every streamed frame teaches the map, so no floaters or washed-out colour."""
    results = run_sparse(replica_room0, "0:20", 0.5, tmp_path)
    assert results["resolution"] == [600, 340]
    assert results["iterations"] > 60 + results["frames"]["streamed"], "non-keyframes are optimised too"
    assert results["streamed"]["psnr"] >= REPLICA_STREAMED_PSNR_FLOOR
    assert results["heldout"]["psnr"] >= REPLICA_HELDOUT_PSNR_FLOOR
    assert results["heldout"]["ssim"] >= REPLICA_SSIM_FLOOR


@pytest.mark.realdata
def test_replica_room0_with_anchor_colours_meets_the_issue_bar(replica_room0, tmp_path):
    """Anchors that start in their cell's colour: Replica's newly seen surface is not washed out."""
    results = run_sparse(replica_room0, "0:20", 0.5, tmp_path, {"model.anchor_colour": True})
    assert results["streamed"]["psnr"] >= REPLICA_ANCHOR_COLOUR_PSNR_FLOOR
    assert results["heldout"]["psnr"] >= REPLICA_ANCHOR_COLOUR_PSNR_FLOOR
    assert results["heldout"]["ssim"] >= REPLICA_ANCHOR_COLOUR_SSIM_FLOOR
