"""The mapper, end to end through ``ogmap run``, judged by image quality.

Floors are set a little below what the code measured (see bench/RESULTS.md), so a regression
fails them. They run on small inputs to keep the suite fast.
"""

import json
import subprocess
import sys

import pytest

from ogmapping.cli.runner import RunOptions, run
from ogmapping.config import resolve

RESULT_KEYS = {"streamed", "heldout", "processing_fps", "snapshot_bytes", "anchors", "gaussians", "device",
               "preset", "resolution"}
# Measured 34.76 dB streamed with the map's moving average (twelfth session), 33.87 without, 31.9 before every frame
# was optimised.
SYNTHETIC_PSNR_FLOOR = 34.4
TSDF_HELDOUT_PSNR_0_99_160 = 18.67  # Open3D TSDF fusion of frames 0-99 at 160x120 (SOURCE.md)
# Measured 25.91 dB held-out, 25.63 streamed (seed 0, seventeenth session's `sparse`: its tenth step per keyframe costs
# these 100 frames 0.1-0.2 dB, seeds 1 / 2 25.70 / 25.39 held-out against 25.82 / 25.62, and gains 0.11 dB on 0-299 at
# 320x240 over eight seeds). 25.99 dB held-out, 25.81 streamed (seed 0, fifteenth session's `sparse`: its third global
# keyframe and half SSIM weight gain on 0-299 but cost these 100 frames 0.2 dB; 26.21 / 26.00 before them, with
# 7-Scenes' colour camera beside the depth camera; 26.48 / 26.50 with the colour camera at the depth camera's centre,
# where seeds 1 and 2 gave 25.58 and 25.86 against 25.92 and 25.26 with it beside). These frames swing by half a decibel
# or more between seeds (anchor colours, 0-99: 26.11 seed 0, 23.61 seed 1; bench/RESULTS.md, "Ninth session"): the floor
# follows one trajectory, not the average.
REAL_160_PSNR_FLOOR = 25.5
# The bar: streamed >= 33, held-out >= 32, SSIM >= 0.95. Measured 33.60 / 33.73 dB, SSIM 0.952 (AMD, fifteenth
# session's `sparse`); 33.68 / 33.78 dB, SSIM 0.955 (twelfth session, the averaged map; 33.64 / 33.64 live); 33.47 /
# 33.50 with refinement to level 2, 31.86 / 31.96 before anchor colours, 22.39 before every frame was optimised.
REPLICA_STREAMED_PSNR_FLOOR = 33.4
REPLICA_HELDOUT_PSNR_FLOOR = 33.5
REPLICA_SSIM_FLOOR = 0.950
# Anchor colours started at the cell's mean colour: measured 34.90 / 34.92 dB streamed / held-out, SSIM 0.962 (fifteenth
# session's `sparse`; 35.19 / 35.29, 0.965 before it, 35.13 / 35.19, 0.964 live).
REPLICA_CELL_START_PSNR_FLOOR = 34.7
REPLICA_CELL_START_SSIM_FLOOR = 0.960
# dense: measured 34.46 / 34.53 dB streamed / held-out, SSIM 0.960 with two torch threads, 34.12 / 34.16, 0.959 with one
# (a dense map's torch calls run on the caller's threads, and its float sums follow their order; fourteenth session;
# 33.98 / 34.07, 0.957 growing at Scaffold-GS's gradient threshold, two threads).
REPLICA_DENSE_PSNR_FLOOR = 33.9
REPLICA_DENSE_SSIM_FLOOR = 0.955
# Measured 26.17 dB held-out, 26.15 streamed on frames 0-59 (fifteenth session's `sparse`); 26.49 / 26.54 with the
# averaged map (26.15 / 26.24 live, 26.04 / 26.13 with refinement to level 2, 25.28 / 25.36 before anchor colours).
REAL_320_PSNR_FLOOR = 26.0


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


def run_preset(data, frames: str, scale: float, out, overrides: dict | None = None, preset: str = "sparse") -> dict:
    """``ogmap run`` of ``preset`` (plus ``overrides``), in process and without progress bars."""
    options = RunOptions(data=str(data), frames=frames, scale=scale, preset=preset, out=out, progress=False)
    return run(options, resolve(preset, overrides=overrides or {}))


@pytest.mark.realdata
def test_seven_scenes_320x240_holds_its_quality(seven_scenes, tmp_path):
    results = run_preset(seven_scenes, "0:60", 0.5, tmp_path)
    assert results["resolution"] == [320, 240]
    assert results["heldout"]["psnr"] >= REAL_320_PSNR_FLOOR
    assert results["streamed"]["psnr"] >= REAL_320_PSNR_FLOOR


@pytest.mark.realdata
def test_replica_room0_at_600x340_is_sharp_and_learns_from_every_frame(replica_room0, tmp_path):
    """The paper's own scene: every streamed frame teaches the map, so no floaters or washed-out colour."""
    results = run_preset(replica_room0, "0:20", 0.5, tmp_path)
    assert results["resolution"] == [600, 340]
    assert results["iterations"] > 80 + results["frames"]["streamed"], "non-keyframes are optimised too"
    assert results["streamed"]["psnr"] >= REPLICA_STREAMED_PSNR_FLOOR
    assert results["heldout"]["psnr"] >= REPLICA_HELDOUT_PSNR_FLOOR
    assert results["heldout"]["ssim"] >= REPLICA_SSIM_FLOOR


@pytest.mark.realdata
def test_replica_room0_with_anchor_colours_started_at_the_cell_colour(replica_room0, tmp_path):
    """Replica's colour and depth are registered, so the cell start is right there and gains more."""
    results = run_preset(replica_room0, "0:20", 0.5, tmp_path, {"model.anchor_colour_start": "cell"})
    assert results["streamed"]["psnr"] >= REPLICA_CELL_START_PSNR_FLOOR
    assert results["heldout"]["psnr"] >= REPLICA_CELL_START_PSNR_FLOOR
    assert results["heldout"]["ssim"] >= REPLICA_CELL_START_SSIM_FLOOR


@pytest.mark.realdata
def test_replica_room0_at_600x340_with_the_dense_preset(replica_room0, tmp_path):
    """The hash-grid version on the paper's scene, so its growth and visible start cannot regress unnoticed."""
    results = run_preset(replica_room0, "0:20", 0.5, tmp_path, preset="dense")
    assert results["preset"] == "dense"
    assert results["streamed"]["psnr"] >= REPLICA_DENSE_PSNR_FLOOR
    assert results["heldout"]["psnr"] >= REPLICA_DENSE_PSNR_FLOOR
    assert results["heldout"]["ssim"] >= REPLICA_DENSE_SSIM_FLOOR
