"""bench/gpu/raster_options.py's smoke run on the CPU: tiny sizes, the gsplat-only sets skipped with the
reason, the others timed and compared, its JSON and table written."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "bench" / "gpu" / "raster_options.py"


def test_the_smoke_run_times_what_the_cpu_can_and_says_why_it_skips_the_rest(tmp_path, capsys, monkeypatch):
    spec = importlib.util.spec_from_file_location("raster_options", SCRIPT)
    bench = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, spec.name, bench)  # its dataclasses look their module up there
    spec.loader.exec_module(bench)
    assert bench.main(["--device", "cpu", "--gaussians", "2000", "--width", "64", "--height", "48",
                       "--steps", "2", "--warmup", "1", "--out", str(tmp_path)]) == 0
    report = json.loads((tmp_path / "raster-options.json").read_text())
    assert (report["backend"], report["width"], report["height"], report["gaussians"]) == ("cpu", 64, 48, 2000)
    options = {entry["name"]: entry for entry in report["options"]}
    assert list(options) == ["baseline", "packed", "absgrad", "antialiased", "selective"]
    for name in ("packed", "absgrad", "antialiased"):
        assert options[name]["skipped"].startswith("gsplat's option; this run renders with the cpu backend")
    for name in ("baseline", "selective"):
        entry = options[name]
        assert entry["skipped"] is None and entry["step_ms_median"] > 0 and 0 < entry["drawn_per_view"] < 2000
        assert 0 <= entry["growth_share"] <= 1 and math.isfinite(entry["psnr_vs_frames_db"])
    # Rows seen in one step and not the next keep Adam's momentum unless the update is selective.
    assert options["baseline"]["psnr_vs_baseline_db"] is None
    assert math.isfinite(options["selective"]["psnr_vs_baseline_db"])
    table = (tmp_path / "raster-options.md").read_text()
    assert "| selective |" in table and "skipped: gsplat's option" in table
    assert "| selective |" in capsys.readouterr().out
