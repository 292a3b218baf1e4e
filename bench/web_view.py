"""What the web view costs the mapping: the same frames through fresh servers with ``--web-port 0``,
with no browser, with a browser page at a fixed pose (it fetches the map after each keyframe and draws
it once: the server's part), with the free-fly page (the browser draws whenever the map changes, on this
machine's CPU when it has no GPU), and with the free-fly page's requests alone, made from Python as
the page makes them (``requests``: the server's part, as with a browser on another machine).

    python bench/web_view.py [--data DIR --format F] [--frames 0:40] [--scale 0.5] [--repeat 2]
        [--pages none pose free-fly requests] [--server-cpus 0] [--json out.json]

With ``--server-cpus`` the server runs on those CPUs and the browser on the others, as a viewer on
another machine would: what is left of a page's cost is the server's own work for it.

Reported per run: the session's processing FPS (``GetStats``), the server process's CPU seconds while the
frames are mapped (what a page adds to them is the view's work, a measure the machine's other load
barely moves, unlike FPS), the web view's decodes and renders with their seconds (they hold the mapper's
lock) and the CPU seconds the server counted for the view's requests (its log line at shutdown); then
each page's means against no page, and the view's own CPU seconds as a share of the server's.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import re
import statistics
import sys
import tempfile
import threading
import time
import urllib.request
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from ogapi.v1 import mapping_pb2 as pb
from ogclient.connection import SessionRef, connect
from ogclient.local_server import LocalServer
from ogclient.messages import frame_to_proto
from ogclient.streaming import stream_frames

from ogmapping.frames.camera import Intrinsics
from ogmapping.quality.evaluation import open_frames

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from tests.service.browser import browser, fragment  # noqa: E402 - the tests' headless chromium

OVERRIDES = {"keyframes.first_iterations": "40", "keyframes.iterations": "8"}  # the demo's
POLL_SECONDS = 0.5  # viewer.js's POLL_MS
PAGES = ("none", "pose", "free-fly", "requests")
BUSY = re.compile(r"web view: (\d+) decodes and renders, ([\d.]+) s; ([\d.]+) CPU seconds")


@dataclass
class Row:
    page: str
    frames: int
    keyframes: int
    processing_fps: float
    decodes_and_renders: int
    web_seconds: float
    # requests only: seconds from a poll that saw a new map version to its splats received (the page
    # sees a keyframe within POLL_SECONDS plus this), the largest and the median
    splats_seconds_max: float | None = None
    splats_seconds_median: float | None = None
    # the server process's CPU seconds (user + system, every thread) from the first frame sent to the last
    # mapped: what the page adds to them is the view's work, whatever else shares the machine (Linux; None
    # elsewhere)
    server_cpu_seconds: float | None = None
    # the CPU seconds the server's log counts for the web view's requests (its decodes and renders included),
    # over the server's whole life (so the page's own files too): the view's work, measured directly
    web_cpu_seconds: float = 0.0


def pin(pid: int, cpus: set[int]) -> None:
    """Every thread of process ``pid`` onto ``cpus`` (threads it starts later inherit their starter's)."""
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(ProcessLookupError):
            os.sched_setaffinity(int(task.name), cpus)


def run(page: str, messages: list[pb.Frame], folder: Path, server_cpus: set[int] | None = None) -> Row:
    with LocalServer(folder / page, "--device", "cpu", "--web-port", "0") as server:
        if server_cpus:
            pin(server.process.pid, server_cpus)
        channel, stub = connect(server.address, timeout=60)
        with channel:
            session = SessionRef.from_credentials(stub.CreateSession(pb.CreateSessionRequest(
                preset="sparse-fast", overrides=OVERRIDES, label=page)))
            url = f"{server.web_url}map/{session.session_id}"
            if page == "pose":
                k = messages[0].color_intrinsics
                camera = Intrinsics(k.fx, k.fy, k.cx, k.cy, k.width, k.height)
                url += fragment(np.array(messages[0].c2w).reshape(4, 4), camera)
            stop = threading.Event()
            opened = threading.Event()
            waits: list[float] = []

            def watch() -> None:
                with browser() as chromium:
                    tab = chromium.new_page(viewport={"width": 640, "height": 480})
                    tab.goto(url)
                    opened.set()
                    stop.wait()

            def request() -> None:
                opened.set()
                fetch_as_the_page_does(server.web_url, session.session_id, stop, waits)

            watcher = threading.Thread(target=request if page == "requests" else watch, daemon=True)
            if page != "none":
                watcher.start()
                opened.wait(60)
            before = cpu_seconds(server.process.pid)
            stream_frames(stub, session, messages, None, False)
            stats = stub.GetStats(pb.GetStatsRequest(session_id=session.session_id), metadata=session.metadata())
            stop.set()
            after = cpu_seconds(server.process.pid)
            cpu = None if before is None or after is None else round(after - before, 2)
            if page != "none":
                watcher.join(60)
    busy = BUSY.findall(server.log_path.read_text())
    count, seconds, web_cpu = busy[-1] if busy else ("0", "0", "0")
    row = Row(page, stats.frames, stats.keyframes, round(stats.processing_fps, 3), int(count), float(seconds),
              server_cpu_seconds=cpu, web_cpu_seconds=float(web_cpu))
    if waits:
        row.splats_seconds_max, row.splats_seconds_median = round(max(waits), 3), round(statistics.median(waits), 3)
    return row


def cpu_seconds(pid: int) -> float | None:
    """A process's user + system CPU seconds so far, all its threads (Linux's /proc), else None."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def fetch_as_the_page_does(web_url: str, map_id: str, stop: threading.Event, waits: list[float]) -> None:
    """The free-fly page's requests (viewer.js): the state every POLL_SECONDS, the map's splats when its
    version changes, the newest keyframe's input and render when it changes; ``waits`` gets each splats
    request's seconds."""
    api = f"{web_url}api/map/{map_id}/"
    version, shown = None, None
    while not stop.wait(POLL_SECONDS):
        with urllib.request.urlopen(api + "state", timeout=30) as response:
            state = json.load(response)
        if state["version"] != version:
            asked = time.perf_counter()
            with urllib.request.urlopen(api + "splats.ply", timeout=30) as response:
                response.read()
                version = int(response.headers["X-Map-Version"])
            waits.append(time.perf_counter() - asked)
        latest = state.get("latest")
        if latest and latest["sensor_ns"] != shown:
            shown = latest["sensor_ns"]
            for part in ("frame", "render.jpg"):
                with urllib.request.urlopen(f"{api}{part}?t={shown}", timeout=30) as response:
                    response.read()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default="synthetic")
    parser.add_argument("--format", default="synthetic")
    parser.add_argument("--frames", default="0:40")
    parser.add_argument("--scale", type=float, default=0.5)
    parser.add_argument("--repeat", type=int, default=2)
    parser.add_argument("--pages", nargs="+", choices=PAGES, default=list(PAGES), help="which to run, in turn")
    parser.add_argument("--server-cpus", type=lambda text: {int(cpu) for cpu in text.split(",")},
                        help="CPUs (e.g. 0 or 0,1) for the server's threads; this script and the browser it "
                             "starts get the others, as a viewer on another machine would (Linux)")
    parser.add_argument("--json")
    args = parser.parse_args()
    if args.server_cpus:
        others = os.sched_getaffinity(0) - args.server_cpus
        if not others or not args.server_cpus <= os.sched_getaffinity(0):
            parser.error(f"--server-cpus must leave some of the CPUs {sorted(os.sched_getaffinity(0))} to the browser")
        pin(os.getpid(), others)
    frames = open_frames(args.data, args.format, args.frames, 1, args.scale)
    messages = [frame_to_proto(frames.load(position)) for position in frames.selection.streamed]
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for _ in range(args.repeat):
            for page in args.pages:
                rows.append(run(page, messages, Path(folder), args.server_cpus))
                print(json.dumps(asdict(rows[-1])), flush=True)
    for line in summary(rows):
        print(line)
    if args.json:
        Path(args.json).write_text(json.dumps([asdict(row) for row in rows], indent=2))
    return 0


def summary(rows: list[Row]) -> list[str]:
    """Each page's mean processing FPS and server CPU seconds over its runs, each with its difference from
    no page and a 95% interval (normal approximation over the runs' spread; the pages run in turn, so slow
    drift hits each alike)."""
    lines = []
    for name, unit, value in (("processing FPS", "", lambda row: row.processing_fps),
                              ("server CPU", " s", lambda row: row.server_cpu_seconds)):
        by_page: dict[str, list[float]] = {}
        for row in rows:
            if value(row) is not None:
                by_page.setdefault(row.page, []).append(value(row))
        base = by_page.get("none")
        for page, values in by_page.items():
            mean = statistics.fmean(values)
            spread = statistics.stdev(values) if len(values) > 1 else 0.0
            line = f"{page}: {name} {mean:.3f}{unit} over {len(values)} runs (sd {spread:.3f})"
            if base and page != "none" and len(base) > 1 and len(values) > 1:
                base_mean = statistics.fmean(base)
                half = 1.96 * (statistics.variance(base) / len(base) + spread**2 / len(values)) ** 0.5
                low, middle, high = (100 * (v / base_mean - 1) for v in (mean - half, mean, mean + half))
                line += f", {middle:+.1f}% against none (95%: {low:+.1f}% to {high:+.1f}%)"
            lines.append(line)
    shares: dict[str, list[float]] = {}
    for row in rows:
        if row.page != "none" and row.server_cpu_seconds:
            shares.setdefault(row.page, []).append(100 * row.web_cpu_seconds / row.server_cpu_seconds)
    for page, values in shares.items():
        lines.append(f"{page}: the web view's own CPU seconds, {statistics.fmean(values):.1f}% of the server's while "
                     f"mapping ({min(values):.1f}% to {max(values):.1f}% over {len(values)} runs)")
    return lines


if __name__ == "__main__":
    sys.exit(main())
