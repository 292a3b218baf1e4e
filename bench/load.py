"""Load benchmark: N sessions streaming at once through one local ogserver.

    python bench/load.py --sessions 1 4 8 --frames 0:20 --scale 0.25 [--preset sparse-fast] [--set KEY=VALUE]
    python bench/load.py --device cuda --data DIR --format 7scenes --frames 0:100 --scale 1   # on a GPU
    python bench/load.py --sessions 1 2 --workers 2   # sessions in 2 worker processes (ogserver --workers 2)

For each N a fresh ``ogserver`` (a subprocess on 127.0.0.1, ``--max-sessions N``, ``--device``: the
CPU unless told) gets N sessions that each stream the same frames (the synthetic scene unless
``--data``) from their own thread, all started together. Reported per N: frames mapped, wall time
from the first send to the last ack, throughput (frames mapped per second over all sessions), each
session's own frames per second (its frames over the time to its last ack; slowest and median), ack
latency percentiles (p50/p95/p99 of the server's ``latency_seconds``: from reading a frame to its
ack, so queueing behind other frames is included), the server's RSS once started and at its peak
(``VmHWM``; with ``--workers``, the server's and its workers' added up), and refused frames; on a GPU
also the memory in use on it (``nvidia-smi``, every
process on that GPU) once the server started and at its peak, and their difference per session.
Prints a Markdown table; ``--json`` writes the figures too.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from contextlib import suppress
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from ogapi.v1 import mapping_pb2 as pb
from ogclient.connection import SessionRef, connect
from ogclient.local_server import LocalServer
from ogclient.messages import frame_to_proto
from ogclient.streaming import stream_frames
from ogserver.cluster.local import descendants

from ogmapping.config import parse_override_args
from ogmapping.datasets import FORMATS
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
    session_fps_min: float = 0.0
    session_fps_median: float = 0.0
    gpu_start_mb: float | None = None
    gpu_peak_mb: float | None = None
    workers: int = 0  # the server's --workers: 0, sessions in threads of its process


def rss_mb(pid: int, field: str) -> float:
    """``field`` of the process and of every process below it (a server's workers), added up."""
    total = 0.0
    for process in (pid, *descendants(pid)):
        with suppress(FileNotFoundError):  # a child that has just exited
            for line in Path(f"/proc/{process}/status").read_text().splitlines():
                if line.startswith(f"{field}:"):
                    total += int(line.split()[1]) / 1024
    return total


def gpu_id(device: str) -> str | None:
    """nvidia-smi's id of the server's GPU (``cuda:N`` through ``CUDA_VISIBLE_DEVICES``), or None on the CPU."""
    if not device.startswith("cuda"):
        return None
    index = int(device.partition(":")[2] or 0)
    visible = os.environ.get("CUDA_VISIBLE_DEVICES", "").strip()
    return visible.split(",")[index].strip() if visible else str(index)


def gpu_used_mb(gpu: str) -> float:
    """Memory in use on one GPU (MiB), by every process on it: nvidia-smi sees the server's CUDA context and
    its allocator's cache, which torch's own counters in the server process do not."""
    query = ["nvidia-smi", f"--id={gpu}", "--query-gpu=memory.used", "--format=csv,noheader,nounits"]
    return float(subprocess.run(query, capture_output=True, text=True, check=True, timeout=10).stdout.split()[0])


class PeakSampler(threading.Thread):
    """The largest value ``read`` returns, sampled every ``interval`` seconds until ``stop``."""

    def __init__(self, read: Callable[[], float], interval: float = 0.2) -> None:
        super().__init__(daemon=True)
        self.read = read
        self.interval = interval
        self.peak = read()
        self.done = threading.Event()

    def run(self) -> None:
        while not self.done.wait(self.interval):
            self.peak = max(self.peak, self.read())

    def stop(self) -> float:
        self.done.set()
        self.join()
        return max(self.peak, self.read())


def run(count: int, frames: list[pb.Frame], request: pb.CreateSessionRequest, record_dir: Path,
        device: str = "cpu", workers: int = 0, torch_threads: int = 0) -> Row:
    gpu = gpu_id(device)
    with LocalServer(record_dir / f"{count}", "--device", device, "--max-sessions", str(count),
                     "--workers", str(workers), "--torch-threads", str(torch_threads)) as server:
        assert server.process is not None
        rss_start = rss_mb(server.process.pid, "VmRSS")
        gpu_start = gpu_used_mb(gpu) if gpu is not None else None
        channel, stub = connect(server.address, timeout=60)
        with channel:
            sessions = [SessionRef.from_credentials(stub.CreateSession(request)) for _ in range(count)]
            results: list = [None] * count
            ends = [0.0] * count
            start = threading.Barrier(count + 1)

            def stream(slot: int) -> None:
                start.wait()
                results[slot] = stream_frames(stub, sessions[slot], frames, progress=False)
                ends[slot] = time.perf_counter()

            threads = [threading.Thread(target=stream, args=(slot,)) for slot in range(count)]
            for thread in threads:
                thread.start()
            sampler = PeakSampler(lambda: gpu_used_mb(gpu)) if gpu is not None else None
            if sampler is not None:
                sampler.start()
            start.wait()
            began = time.perf_counter()
            for thread in threads:
                thread.join()
            seconds = time.perf_counter() - began
            gpu_peak = sampler.stop() if sampler is not None else None
            rss_peak = rss_mb(server.process.pid, "VmHWM")
    latencies = np.array([ack.latency_seconds for result in results for ack in result.mapped])
    mapped = len(latencies)
    p50, p95, p99 = np.percentile(latencies, [50, 95, 99]) if mapped else (0.0, 0.0, 0.0)
    refused = sum(len(result.rejected) for result in results)
    per_session = [len(result.mapped) / (end - began) for result, end in zip(results, ends, strict=True)]
    return Row(count, mapped, refused, seconds, mapped / seconds, float(p50), float(p95), float(p99), rss_start,
               rss_peak, min(per_session), float(np.median(per_session)), gpu_start, gpu_peak, workers)


def table(rows: list[Row]) -> str:
    on_gpu = any(row.gpu_start_mb is not None for row in rows)
    lines = [
        "| sessions | frames mapped | refused | wall s | throughput frames/s | per-session frames/s slowest / median "
        "| ack latency p50 / p95 / p99 s | server RSS started / peak MB |"
        + (" GPU MB started / peak / per session |" if on_gpu else ""),
        "|---|---|---|---|---|---|---|---|" + ("---|" if on_gpu else ""),
    ]
    for row in rows:
        line = (
            f"| {row.sessions} | {row.frames} | {row.refused} | {row.seconds:.1f} | {row.frames_per_second:.2f} "
            f"| {row.session_fps_min:.2f} / {row.session_fps_median:.2f} "
            f"| {row.latency_p50:.2f} / {row.latency_p95:.2f} / {row.latency_p99:.2f} "
            f"| {row.rss_start_mb:.0f} / {row.rss_peak_mb:.0f} |"
        )
        if on_gpu:
            gpu = (f" {row.gpu_start_mb:.0f} / {row.gpu_peak_mb:.0f} / "
                   f"{(row.gpu_peak_mb - row.gpu_start_mb) / row.sessions:.0f} |"
                   if row.gpu_start_mb is not None and row.gpu_peak_mb is not None else " – |")
            line += gpu
        lines.append(line)
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sessions", type=int, nargs="+", default=[1, 4, 8], help="concurrent sessions (1 4 8)")
    parser.add_argument("--device", default="cpu", help="the server's --device: cpu, cuda or cuda:N (cpu)")
    parser.add_argument("--data", default="synthetic", help="dataset folder streamed by every session (synthetic)")
    parser.add_argument("--format", default="auto", choices=FORMATS, help="dataset layout (default: detect)")
    parser.add_argument("--frames", default="0:20", help="frames, as ogmap's --frames (0:20: 18 streamed)")
    parser.add_argument("--scale", type=float, default=0.25,
                        help="image scale (0.25: the synthetic scene's 320x240 as 80x60)")
    parser.add_argument("--preset", default="sparse-fast", help="session preset (sparse-fast)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="config override for every session (repeatable)")
    parser.add_argument("--workers", type=int, default=0,
                        help="the server's --workers: sessions in this many worker processes (0: threads)")
    parser.add_argument("--torch-threads", type=int, default=0,
                        help="the server's --torch-threads, split between its workers (0: min(cores, 8))")
    parser.add_argument("--json", help="also write the figures here")
    args = parser.parse_args(argv)
    frame_set = open_frames(args.data, args.format, args.frames, 1, args.scale)
    frames = [frame_to_proto(frame_set.load(position)) for position in frame_set.selection.streamed]
    request = pb.CreateSessionRequest(preset=args.preset, overrides=parse_override_args(args.overrides), label="load")
    rows = []
    with tempfile.TemporaryDirectory(prefix="ogload-") as folder:
        for count in args.sessions:
            rows.append(run(count, frames, request, Path(folder), args.device, args.workers, args.torch_threads))
            print(f"{count} sessions: {rows[-1].frames_per_second:.2f} frames/s", file=sys.stderr, flush=True)
    print(f"server: {f'--workers {args.workers}' if args.workers else 'sessions in threads'}"
          f"{f', --torch-threads {args.torch_threads}' if args.torch_threads else ''}")
    print(table(rows))
    if args.json:
        Path(args.json).write_text(json.dumps([asdict(row) for row in rows], indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
