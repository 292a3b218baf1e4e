"""What cluster mode costs: the same frames and renders through a single ogserver and through a
front-end whose session lives in a Ray actor, in one run.

    python bench/cluster.py --frames 0:20 --scale 0.25 [--renders 20] [--set KEY=VALUE ...]

A local Ray cluster of one node (``ogserver.cluster.local``) and three servers on 127.0.0.1, one after
the other: a single ``ogserver``, an ``ogserver --cluster`` (record dir shared as a path), and one with
``--shared-storage file://...`` (each flush also uploaded as a part through fsspec, as to s3://).
For each, one session (preset ``sparse-fast``, no optimisation unless ``--set`` asks for it, so the
figures are the plumbing, not the mapping) gets the synthetic frames twice: in lockstep (the next
frame is sent once the previous one's ack arrived: the client-side round trip per frame) and as one
pipelined stream (throughput, frames per second over the whole stream). Then ``--renders`` renders
from the first frame's pose (the client-side time per render). Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import queue
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from ogapi.v1 import mapping_pb2 as pb
from ogapi.v1 import mapping_pb2_grpc as pb_grpc
from ogclient.connection import SessionRef, connect
from ogclient.evaluation import render
from ogclient.local_server import LocalServer
from ogclient.messages import frame_to_proto
from ogclient.streaming import stream_frames
from ogserver.cluster.local import local_cluster

from ogmapping.config import parse_override_args
from ogmapping.quality.evaluation import open_frames

NO_OPTIMISATION = {"keyframes.first_iterations": "0", "keyframes.iterations": "0"}


@dataclass
class Row:
    server: str
    frame_ms_p50: float
    frame_ms_p95: float
    stream_fps: float
    render_ms_p50: float


def lockstep(stub: pb_grpc.MappingStub, session: SessionRef, frames: list[pb.Frame]) -> list[float]:
    """Seconds from sending each frame to its ack, one frame in flight at a time."""
    acked: queue.SimpleQueue[None] = queue.SimpleQueue()
    sent: list[float] = []

    def one_at_a_time() -> Iterator[pb.Frame]:
        for frame in frames:
            sent.append(time.perf_counter())
            yield frame
            acked.get()

    times = []
    for ack in stub.StreamFrames(one_at_a_time(), metadata=session.stream_metadata()):
        assert ack.accepted, ack.error.message
        times.append(time.perf_counter() - sent[len(times)])
        acked.put(None)
    return times


def measure(name: str, address: str, frames: list[pb.Frame], overrides: dict[str, str], renders: int,
            pose: np.ndarray, camera: object) -> Row:
    channel, stub = connect(address, timeout=120.0)
    try:
        request = pb.CreateSessionRequest(preset="sparse-fast", overrides=overrides, label=f"bench-{name}")
        session = SessionRef.from_credentials(stub.CreateSession(request))
        per_frame = lockstep(stub, session, frames)
        streamed = stream_frames(stub, session, frames, progress=False)
        render_times = []
        for _ in range(renders):
            start = time.perf_counter()
            render(stub, session, pose, camera)
            render_times.append(time.perf_counter() - start)
        stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id), metadata=session.metadata())
    finally:
        channel.close()
    return Row(name, 1000 * float(np.median(per_frame)), 1000 * float(np.percentile(per_frame, 95)),
               len(frames) / streamed.seconds, 1000 * float(np.median(render_times)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", default="0:20")
    parser.add_argument("--scale", type=float, default=0.25)
    parser.add_argument("--renders", type=int, default=20)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="session config overrides")
    args = parser.parse_args()
    overrides = {**NO_OPTIMISATION, **parse_override_args(args.set)}
    frame_set = open_frames("synthetic", "synthetic", args.frames, 1, args.scale, n_frames=40)
    loaded = [frame_set.load(position) for position in frame_set.selection.streamed]
    frames = [frame_to_proto(frame) for frame in loaded]
    common = ("--device", "cpu", "--no-warm-up", "--torch-threads", "1")
    rows = []
    with tempfile.TemporaryDirectory(prefix="ogbench-") as work:
        root = Path(work)
        with local_cluster(root, workers=0, cpus_per_node=1) as cluster:
            servers = (("single server", ()), ("front-end + Ray actor", ("--cluster", cluster.address)),
                       ("front-end + Ray actor, fsspec file:// storage",
                        ("--cluster", cluster.address, "--shared-storage", (root / "store").as_uri())))
            for name, extra in servers:
                record_dir = root / f"recordings{len(rows)}"
                with LocalServer(record_dir, *common, *extra) as server:
                    rows.append(measure(name, server.address, frames, overrides, args.renders, loaded[0].c2w,
                                        loaded[0].color_intrinsics))
    print(f"{len(frames)} frames of {loaded[0].rgb.shape[1]}x{loaded[0].rgb.shape[0]}, overrides {overrides}\n")
    print("| server | per frame, lockstep p50 (ms) | p95 (ms) | pipelined stream (frames/s) | render p50 (ms) |")
    print("|---|---|---|---|---|")
    for row in rows:
        print(f"| {row.server} | {row.frame_ms_p50:.1f} | {row.frame_ms_p95:.1f} | {row.stream_fps:.1f} | "
              f"{row.render_ms_p50:.1f} |")


if __name__ == "__main__":
    main()
