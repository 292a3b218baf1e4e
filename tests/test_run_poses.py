"""``ogmap trajectory``, and ``ogmap run`` mapping with a trajectory file's poses (``--poses``) and judging
at a second, exact one (``--eval-poses``), on a few tiny synthetic frames."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from safetensors import safe_open

from ogmapping.cli.commands import main
from ogmapping.cli.pose_log import PoseLog
from ogmapping.datasets.synthetic import trajectory as synthetic_trajectory
from ogmapping.frames.trajectory import pose_errors, read_tum
from ogmapping.optim.poses import PoseReport
from ogmapping.queries import KeyframePose

DATA = ["--data", "synthetic", "--format", "synthetic", "--frames", "0:6", "--scale", "0.25"]
FAST = ["--set", "keyframes.first_iterations=3", "--set", "keyframes.iterations=2", "--device", "cpu", "--quiet"]
SPLITS = ("streamed", "heldout")


def ogmap(*args: str | Path) -> int:
    return main([str(arg) for arg in args])


def tensors(path: Path) -> tuple[dict, dict[str, bytes]]:
    """A snapshot's metadata and tensor bytes (the file orders its metadata keys as it likes)."""
    with safe_open(str(path), "np") as snapshot:
        return snapshot.metadata(), {key: snapshot.get_tensor(key).tobytes() for key in snapshot.keys()}  # noqa: SIM118


def results(folder: Path) -> dict:
    return json.loads((folder / "results.json").read_text())


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The exact and a noisy trajectory, and a run on the data's poses judged at the exact file's too."""
    root = tmp_path_factory.mktemp("poses")
    assert ogmap("trajectory", *DATA, "--quiet", "--out", root / "exact.tum") == 0
    assert ogmap("trajectory", *DATA, "--quiet", "--noise-translation", "0.01", "--noise-rotation", "0.5",
                 "--noise-seed", "1", "--out", root / "noisy.tum") == 0
    assert ogmap("run", *DATA, *FAST, "--eval-poses", root / "exact.tum", "--out", root / "data") == 0
    return root


def test_trajectory_writes_every_selected_frame_and_noise_moves_all_but_the_first(
    runs: Path, capsys: pytest.CaptureFixture,
) -> None:
    exact, noisy = read_tum(runs / "exact.tum"), read_tum(runs / "noisy.tum")
    assert exact.keys.tolist() == [i / 30.0 for i in range(6)]  # streamed 0-4 and held-out 5, keyed by timestamp
    np.testing.assert_allclose(exact.poses, synthetic_trajectory(100)[:6], rtol=0, atol=1e-15)
    distances, angles = pose_errors(noisy.poses, exact.poses)
    assert distances[0] < 1e-15 and angles[0] < 1e-5
    assert (distances[1:] > 1e-4).all() and (angles[1:] > 1e-3).all()
    assert "noise: 0.01 m per axis, 0.5 deg about a random axis, seed 1" in (runs / "noisy.tum").read_text()
    assert ogmap("trajectory", *DATA, "--quiet", "--noise-seed", "2", "--noise-rotation", "0.5",
                 "--out", runs / "again.tum") == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith(f"wrote 6 poses (5 streamed, 1 held out) to {runs / 'again.tum'}; noise seed 2: mean error "
                           "0.00 cm, ")


def test_judging_at_the_data_s_own_trajectory_scores_as_the_normal_judging(runs: Path) -> None:
    scores = results(runs / "data")
    assert scores["poses"] is None
    assert scores["at_eval_poses"] == {**{split: scores[split] for split in SPLITS}, "poses": str(runs / "exact.tum")}
    previews = {path.name for path in (runs / "data").glob("*.png")}
    assert {"streamed_000000.png", "heldout_000005.png", "at_eval_poses_streamed_000000.png",
            "at_eval_poses_heldout_000005.png"} <= previews


def test_mapping_with_the_exact_trajectory_file_makes_the_same_map(runs: Path) -> None:
    out = runs / "exact"
    assert ogmap("run", *DATA, *FAST, "--poses", runs / "exact.tum", "--out", out) == 0
    assert tensors(out / "map.safetensors") == tensors(runs / "data" / "map.safetensors")
    scores, baseline = results(out), results(runs / "data")
    assert scores["poses"] == str(runs / "exact.tum") and "at_eval_poses" not in scores
    assert {split: scores[split] for split in SPLITS} == {split: baseline[split] for split in SPLITS}


def test_a_map_from_noisy_poses_is_judged_at_them_and_at_the_exact_ones(runs: Path) -> None:
    out = runs / "noisy"
    assert ogmap("run", *DATA, *FAST, "--poses", runs / "noisy.tum", "--eval-poses", runs / "exact.tum",
                 "--out", out) == 0
    assert tensors(out / "map.safetensors") != tensors(runs / "data" / "map.safetensors")
    scores = results(out)
    at_exact = scores["at_eval_poses"]
    for split in SPLITS:
        assert at_exact[split]["frames"] == scores[split]["frames"]
        assert at_exact[split]["psnr"] != scores[split]["psnr"]
    assert (out / "at_eval_poses_streamed_000004.png").read_bytes() != (out / "streamed_000004.png").read_bytes()


def test_a_frame_missing_from_a_trajectory_file_stops_the_run_before_mapping(
    tmp_path: Path, capsys: pytest.CaptureFixture,
) -> None:
    short = tmp_path / "short.tum"
    assert ogmap("trajectory", *DATA[:-4], "--frames", "0:4", "--quiet", "--out", short) == 0
    for flag in ("--poses", "--eval-poses"):
        out = tmp_path / flag.strip("-")
        assert ogmap("run", *DATA, *FAST, flag, short, "--out", out) == 2
        error = capsys.readouterr().err.strip()
        assert error == f"ogmap: error: {short} has no pose for frame 4 (timestamp 0.13333333333333333)"
        assert not out.exists()


def test_a_bad_trajectory_file_or_noise_is_a_one_line_error(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    bad = tmp_path / "bad.tum"
    bad.write_text("0 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 1\n")
    assert ogmap("run", *DATA, *FAST, "--poses", bad, "--out", tmp_path / "out") == 2
    assert capsys.readouterr().err.strip() == (f"ogmap: error: {bad}:2: expected 8 fields "
                                               "(timestamp tx ty tz qx qy qz qw), got 7")
    assert ogmap("run", *DATA, *FAST, "--eval-poses", tmp_path / "missing.tum", "--out", tmp_path / "out") == 2
    assert "missing.tum" in capsys.readouterr().err
    assert ogmap("trajectory", *DATA, "--quiet", "--noise-translation", "-1", "--out", tmp_path / "t.tum") == 2
    assert capsys.readouterr().err.strip() == ("ogmap: error: translation noise must be a finite number >= 0 metres, "
                                               "got -1.0")
    assert not (tmp_path / "t.tum").exists()


def test_a_refining_run_writes_its_trajectory_and_scores_its_poses_against_the_exact_ones(runs: Path) -> None:
    out = runs / "refined"
    assert ogmap("run", *DATA, *FAST, "--set", "poses.refine=true", "--poses", runs / "noisy.tum",
                 "--eval-poses", runs / "exact.tum", "--out", out) == 0
    refinement = results(out)["pose_refinement"]
    refined, noisy = read_tum(out / refinement["trajectory"]), read_tum(runs / "noisy.tum")
    assert refined.keys.tolist() == noisy.keys[:5].tolist()  # the streamed frames
    # The first keyframe stays the client's (up to the mapper's float32).
    np.testing.assert_allclose(refined.poses[0], noisy.poses[0], rtol=0, atol=1e-6)
    corrections, _ = pose_errors(refined.poses, noisy.poses[:5])
    assert refinement["per_frame"]["correction_cm"] == pytest.approx((100 * corrections).tolist())
    assert refinement["max_correction_cm"] > 0 and refinement["clamped_frames"] == 0
    assert refinement["given_error_cm"] == pytest.approx(
        100 * pose_errors(noisy.poses[:5], read_tum(runs / "exact.tum").poses[:5])[0].mean())
    assert len(refinement["per_frame"]["refined_error_cm"]) == 5


def test_a_frame_without_a_correction_of_its_own_is_reported_moved_as_its_nearest_keyframe() -> None:
    def pose(x: float, y: float = 0.0) -> np.ndarray:
        c2w = np.eye(4)
        c2w[:2, 3] = x, y
        return c2w

    # Keyframes 0 and 4; refinement moved keyframe 4 by a centimetre along y.
    keyframes = [KeyframePose(0, pose(0.0), pose(0.0), False), KeyframePose(4, pose(0.4), pose(0.4, 0.01), False)]
    for follow, last in ((False, 0.0), (True, 0.01)):
        log = PoseLog()
        for index in range(6):
            frame = SimpleNamespace(index=index, timestamp=float(index), c2w=pose(0.1 * index))
            log.add(frame, SimpleNamespace(pose=PoseReport.unrefined(frame.c2w)))
        log.settle(keyframes, follow_nearest=follow)
        # Frames 0-2 are nearest keyframe 0, 3-5 keyframe 4 (itself at its final pose either way).
        assert [round(refined[1, 3], 6) for refined in log.refined] == [0.0, 0.0, 0.0, last, 0.01, last]
        assert np.allclose([refined[0, 3] for refined in log.refined], [0.1 * index for index in range(6)])
