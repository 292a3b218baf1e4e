"""Markdown tables from ``ogmap run`` results.json files, beside the paper's Replica speeds.

Usage: ``python bench/gpu/table.py OUT/dense OUT/sparse OUT/sparse-fast`` (folders or results.json): one
table; ``python bench/gpu/table.py --tree RESULTS`` (a folder that ``check.sh`` filled): the machine, one
table of every results.json below it, labelled by its folder, then the load tables (``load/load.md``), the
rasterizer options' tables (``raster-options/**/raster-options.md``), the mapping step's figures
(``gpu-tests/step-time.json``, ``gpu-tests/sync-sites.json``), the Triton kernels' timings
(``gpu-tests/triton-loss.json``, ``gpu-tests/triton-decode.json``), the frame preparation's
(``gpu-tests/preprocess-device.json``) and the GPU tests' summary
(``gpu-tests/pytest.txt``).
The paper's processing FPS were measured on Replica at 1200x680 with an RTX 4090 (its Table "key
performance metrics on Replica"); beside other data, resolutions or GPUs they are context only.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path
from typing import Any

PAPER_REPLICA_FPS = {"dense": 5.6, "sparse": 8.5, "sparse-fast": 16.1}
KERNEL_TIMINGS = {
    "triton-loss.json": "The loss forward and backward, Triton kernels against torch (tests/test_gpu_triton_loss.py)",
    "triton-decode.json": "The decode forward and backward, Triton kernels against torch "
                          "(tests/test_gpu_triton_decode.py)",
    "preprocess-device.json": "A frame's depth registered and clipped on the device, against numpy on the host "
                              "(tests/test_gpu_preprocess.py)",
}
COLUMNS = (
    "run",
    "preset",
    "device, backend",
    "resolution",
    "frames streamed / held-out",
    "processing FPS",
    "paper FPS (Replica, 4090)",
    "render FPS",
    "PSNR streamed / held-out",
    "SSIM streamed / held-out",
    "MS-SSIM streamed / held-out",
    "LPIPS streamed / held-out",
    "depth L1 cm streamed / held-out",
    "snapshot MB",
    "peak GPU MB",
    "peak GPU MB every 100 frames",
)
SUMMARY_LINE = re.compile(r"^(PASSED|FAILED|ERROR|SKIPPED|XFAIL|XPASS)\b"
                          r"|\b(passed|failed|errors?|skipped|xfailed|xpassed)\b.* in [0-9.]+s")


def load(path: Path) -> dict[str, Any]:
    return json.loads((path / "results.json" if path.is_dir() else path).read_text())


def label(path: Path, root: Path | None = None) -> str:
    """The run's name: its folder, relative to ``root`` when given."""
    folder = path if path.is_dir() else path.parent
    return folder.relative_to(root).as_posix() if root is not None else folder.name


def number(value: Any, digits: int) -> str:
    return "–" if value is None else f"{value:.{digits}f}"


def pair(result: dict[str, Any], key: str, digits: int) -> str:
    streamed = (result.get("streamed") or {}).get(key)
    heldout = (result.get("heldout") or {}).get(key)
    return f"{number(streamed, digits)} / {number(heldout, digits)}"


def megabytes(value: Any) -> str:
    return "–" if value is None else f"{value / 1e6:.1f}"


def row(name: str, result: dict[str, Any]) -> list[str]:
    preset = result.get("preset", "?")
    width, height = result.get("resolution") or ("?", "?")
    frames = result.get("frames") or {}
    on_gpu = str(result.get("device", "")).startswith("cuda")
    memory = [megabytes(entry.get("peak_gpu_memory_bytes")) for entry in result.get("memory_per_100_frames", [])]
    return [
        name,
        preset,
        f"{result.get('device', '?')}, {result.get('backend', '–')}",
        f"{width}x{height}",
        f"{frames.get('streamed', '–')} / {frames.get('heldout', '–')}",
        number(result.get("processing_fps"), 2),
        number(PAPER_REPLICA_FPS.get(preset) if on_gpu else None, 1),
        number(result.get("render_fps"), 1),
        pair(result, "psnr", 2),
        pair(result, "ssim", 3),
        pair(result, "ms_ssim", 3),
        pair(result, "lpips", 3),
        pair(result, "depth_l1_cm", 2),
        megabytes(result.get("snapshot_bytes")),
        megabytes(result.get("peak_gpu_memory_bytes")),
        " / ".join(memory) if on_gpu and memory else "–",
    ]


def described(value: Any) -> str:
    """A JSON value on one line: ``key: value; ...``, nested objects in parentheses."""
    if isinstance(value, dict):
        return "; ".join(f"{key}: {nested(item)}" for key, item in value.items())
    if isinstance(value, list):
        return ", ".join(nested(item) for item in value)
    return str(value)


def nested(value: Any) -> str:
    return f"({described(value)})" if isinstance(value, dict) else described(value)


def table(runs: list[tuple[str, dict[str, Any]]]) -> str:
    """One row per (name, results.json); below it every distinct ``machine`` the results name."""
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(row(name, result)) + " |" for name, result in runs]
    machines = dict.fromkeys(f"- machine: {described(r['machine'])}" for _, r in runs if r.get("machine"))
    return "\n".join([*lines, "", *machines, "- MB = 10^6 bytes; PSNR in dB; frames streamed / held-out."])


def natural(text: str) -> list[Any]:
    """Sort key that puts threads-2 before threads-16."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", text)]


def step_figures(report: Path) -> list[str]:
    """The mapping step's figures (tests/test_gpu_step.py), the Triton kernels' timings and how the
    synchronisation check fared."""
    lines = []
    timing = report / "step-time.json"
    if timing.exists():
        lines += ["## One mapping step in steady state (tests/test_gpu_step.py)", ""]
        lines += [f"- {key}: {described(value)}" for key, value in json.loads(timing.read_text()).items()]
        lines.append("")
    for name, title in KERNEL_TIMINGS.items():
        kernels = report / name
        if kernels.exists():
            lines += [f"## {title}", ""]
            lines += [f"- {key}: {described(value)}" for key, value in json.loads(kernels.read_text()).items()]
            lines.append("")
    sync = report / "sync-sites.json"
    if sync.exists():
        lines += ["Host synchronisations per step under `torch.cuda.set_sync_debug_mode(\"warn\")`, by site:", "",
                  "```", sync.read_text().rstrip(), "```", ""]
    output = report / "pytest.txt"
    if output.exists():
        summary = [line for line in output.read_text().splitlines() if SUMMARY_LINE.search(line)]
        lines += ["## pytest -m gpu", "", "```", *summary, "```", ""]
    return lines


def tree(root: Path) -> str:
    """table.md of a results folder that check.sh filled."""
    runs = [(label(path, root), load(path)) for path in root.rglob("results.json")]
    runs.sort(key=lambda run: natural(run[0]))
    lines = [f"# {root.name}", ""]
    if runs:
        lines += [table(runs), ""]
    for load_table in sorted((root / "load").glob("load*.md"), key=lambda path: (path.stem != "load", path.stem)):
        how = "threads" if load_table.stem == "load" else load_table.stem.removeprefix("load-").replace("-", " ")
        lines += [f"## Sessions on one server, {how} (bench/load.py)", "", load_table.read_text().rstrip(), ""]
    for options in sorted((root / "raster-options").rglob("raster-options.md")):
        lines += ["## Rasterizer options and selective Adam (bench/gpu/raster_options.py)", "",
                  options.read_text().rstrip(), ""]
    lines += step_figures(root / "gpu-tests")
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    if argv[:1] == ["--tree"] and len(argv) == 2:
        print(tree(Path(argv[1])))
        return 0
    if not argv or argv[0].startswith("-"):
        print(__doc__, file=sys.stderr)
        return 2
    print(table([(label(Path(path)), load(Path(path))) for path in argv]))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
