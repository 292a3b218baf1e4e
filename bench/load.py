"""Load benchmark: N sessions streaming at once through one local ogserver.

    python bench/load.py --sessions 1 4 8 --frames 0:20 --scale 0.25 [--preset sparse-fast] [--set KEY=VALUE]

For each N a fresh ``ogserver`` (a subprocess on 127.0.0.1, ``--max-sessions N``, CPU) gets N
sessions that each stream the same synthetic frames from their own thread, all started together.
Reported per N: frames mapped, wall time from the first send to the last ack, throughput (frames
mapped per second over all sessions), ack latency percentiles (p50/p95/p99 of the server's
``latency_seconds``: from reading a frame to its ack, so queueing behind other frames is
included), the server's RSS once started and at its peak (``VmHWM``), and refused frames. Prints
a Markdown table; ``--json`` writes the figures too.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from ogapi.v1 import mapping_pb2 as pb
from ogclient.connection import SessionRef, connect
from ogclient.local_server import LocalServer
from ogclient.messages import frame_to_proto
from ogclient.streaming import stream_frames

from ogmapping.config import parse_override_args
from ogmapping.quality.evaluation import open_frames


@dataclass
class Row:
    sessions: int
    frames: int
    refused: int
    seconds: float
    frames_per_second: float
    latency_p50: float
    latency_p95: float
    latency_p99: float
    rss_start_mb: float
    rss_peak_mb: float


def rss_mb(pid: int, field: str) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(f"{field}:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError(f"no {field} for process {pid}")


def run(count: int, frames: list[pb.Frame], request: pb.CreateSessionRequest, record_dir: Path) -> Row:
    with LocalServer(record_dir / f"{count}", "--device", "cpu", "--max-sessions", str(count)) as server:
        assert server.process is not None
        rss_start = rss_mb(server.process.pid, "VmRSS")
        channel, stub = connect(server.address, timeout=60)
        with channel:
            sessions = [SessionRef.from_credentials(stub.CreateSession(request)) for _ in range(count)]
            results: list = [None] * count
            start = threading.Barrier(count + 1)

            def stream(slot: int) -> None:
                start.wait()
                results[slot] = stream_frames(stub, sessions[slot], frames, progress=False)

            threads = [threading.Thread(target=stream, args=(slot,)) for slot in range(count)]
            for thread in threads:
                thread.start()
            start.wait()
            began = time.perf_counter()
            for thread in threads:
                thread.join()
            seconds = time.perf_counter() - began
            rss_peak = rss_mb(server.process.pid, "VmHWM")
    latencies = np.array([ack.latency_seconds for result in results for ack in result.mapped])
    mapped = len(latencies)
    p50, p95, p99 = np.percentile(latencies, [50, 95, 99]) if mapped else (0.0, 0.0, 0.0)
    refused = sum(len(result.rejected) for result in results)
    return Row(count, mapped, refused, seconds, mapped / seconds, float(p50), float(p95), float(p99), rss_start,
               rss_peak)


def table(rows: list[Row]) -> str:
    lines = [
        "| sessions | frames mapped | refused | wall s | throughput frames/s | ack latency p50 / p95 / p99 s "
        "| server RSS started / peak MB |",
        "|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        lines.append(
            f"| {row.sessions} | {row.frames} | {row.refused} | {row.seconds:.1f} | {row.frames_per_second:.2f} "
            f"| {row.latency_p50:.2f} / {row.latency_p95:.2f} / {row.latency_p99:.2f} "
            f"| {row.rss_start_mb:.0f} / {row.rss_peak_mb:.0f} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sessions", type=int, nargs="+", default=[1, 4, 8], help="concurrent sessions (1 4 8)")
    parser.add_argument("--frames", default="0:20", help="synthetic frames, as ogmap's --frames (0:20: 18 streamed)")
    parser.add_argument("--scale", type=float, default=0.25, help="image scale of the 320x240 scene (0.25)")
    parser.add_argument("--preset", default="sparse-fast", help="session preset (sparse-fast)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="config override for every session (repeatable)")
    parser.add_argument("--json", help="also write the figures here")
    args = parser.parse_args(argv)
    frame_set = open_frames("synthetic", "synthetic", args.frames, 1, args.scale)
    frames = [frame_to_proto(frame_set.load(position)) for position in frame_set.selection.streamed]
    request = pb.CreateSessionRequest(preset=args.preset, overrides=parse_override_args(args.overrides), label="load")
    rows = []
    with tempfile.TemporaryDirectory(prefix="ogload-") as folder:
        for count in args.sessions:
            rows.append(run(count, frames, request, Path(folder)))
            print(f"{count} sessions: {rows[-1].frames_per_second:.2f} frames/s", file=sys.stderr, flush=True)
    print(table(rows))
    if args.json:
        Path(args.json).write_text(json.dumps([asdict(row) for row in rows], indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
