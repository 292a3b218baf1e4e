"""Live benchmark: what the live view costs the mapping, and a 30 FPS stream in realtime mode.

    python bench/live.py --data ../shared/data/7scenes-redkitchen --frames 0:100 --scale 0.5 \
        [--preset sparse] [--fps 30] [--json live.json]

Views: the same frames, streamed as fast as the server takes them, through three fresh servers:
``--view-seconds 0`` (no views at all), the default (keyframes' render and point cloud into the
recording, at most one a second), and ``--foxglove-port 0`` with a Foxglove client subscribed to
every topic of the session (renders, transforms, input images and point clouds, one look a second).
Reported: the session's processing FPS (``GetStats``), the live view thread's busy time (its log
line at shutdown) and what the Foxglove client received.

Realtime: the frames sent at ``--fps`` (pre-encoded, on a fixed schedule) into a realtime session,
then into a default (lossless) one: the rate the client kept, frames mapped and skipped, and the ack
latency (the server's ``latency_seconds``, receipt to ack) of all frames and of the mapped ones.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import re
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
from ogclient.streaming import paced, stream_frames
from ogserver.live.publisher import LIVE_TOPICS, session_prefix

from ogmapping.quality.evaluation import open_frames

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from tests.service import foxglove_client  # noqa: E402 - the protocol client the tests use


@dataclass
class ViewRow:
    views: str
    frames: int
    processing_fps: float
    keyframes: int
    view_seconds: float  # the live view thread's time making and publishing views (from the server's log)
    looks: int
    received: dict[str, int]  # Foxglove messages by topic (without the session prefix)


@dataclass
class StreamRow:
    mode: str
    frames: int
    send_seconds: float
    sent_fps: float
    mapped: int
    skipped: int
    latency_p50: float
    latency_p95: float
    latency_max: float
    mapped_latency_p50: float
    mapped_latency_max: float


def stats(stub, session: SessionRef) -> pb.Stats:
    return stub.GetStats(pb.GetStatsRequest(session_id=session.session_id), metadata=session.metadata())


def views_run(name: str, frames: list[pb.Frame], request: pb.CreateSessionRequest, record_dir: Path,
              *flags: str) -> ViewRow:
    with LocalServer(record_dir / name, "--device", "cpu", *flags) as server:
        channel, stub = connect(server.address, timeout=60)
        with channel:
            session = SessionRef.from_credentials(stub.CreateSession(request))
            received: dict[str, int] = {}
            watcher = None
            if "--foxglove-port" in flags:
                port = int(re.search(r"Foxglove live view on ws://[^:]+:(\d+)", server.log_path.read_text())[1])
                prefix = session_prefix(session.session_id)
                result: list = []

                def watch() -> None:
                    result.append(asyncio.run(foxglove_client.watch(
                        f"ws://127.0.0.1:{port}", prefix, list(LIVE_TOPICS), set(), 3600)))

                watcher = threading.Thread(target=watch, daemon=True)
                watcher.start()
                time.sleep(3.0)  # the session's topics are advertised within a second; the client subscribes
            stream_frames(stub, session, frames, progress=False)
            final = stats(stub, session)
            if watcher is not None:
                # The watcher returns when its connection ends: stopping the server ends it.
                server.stop()
                watcher.join(30)
                received = {topic[len(prefix):]: len(items) for topic, items in result[0].messages.items()}
    busy = re.search(r"live view: (\d+) session looks, ([0-9.]+) s", server.log_path.read_text())
    looks, seconds = (int(busy[1]), float(busy[2])) if busy else (0, 0.0)
    return ViewRow(name, int(final.frames), final.processing_fps, int(final.keyframes), seconds, looks, received)


def stream_run(mode: str, frames: list[pb.Frame], request: pb.CreateSessionRequest, fps: float,
               record_dir: Path) -> StreamRow:
    with LocalServer(record_dir / mode, "--device", "cpu") as server:
        channel, stub = connect(server.address, timeout=60)
        with channel:
            session = SessionRef.from_credentials(stub.CreateSession(request))
            sent: list[float] = []

            def sensor():
                for message in paced(frames, fps):
                    sent.append(time.monotonic())
                    yield message

            result = stream_frames(stub, session, sensor(), progress=False)
    latencies = np.array([ack.latency_seconds for ack in result.acks if ack.accepted])
    mapped = np.array([ack.latency_seconds for ack in result.mapped])
    seconds = sent[-1] - sent[0]
    return StreamRow(mode, len(frames), seconds, (len(sent) - 1) / seconds, len(result.mapped), len(result.skipped),
                     float(np.percentile(latencies, 50)), float(np.percentile(latencies, 95)), float(latencies.max()),
                     float(np.percentile(mapped, 50)), float(mapped.max()))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", default="../shared/data/7scenes-redkitchen")
    parser.add_argument("--frames", default="0:100")
    parser.add_argument("--scale", type=float, default=0.5)
    parser.add_argument("--preset", default="sparse")
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--repeat", type=int, default=1, help="run the three view servers this many times")
    parser.add_argument("--skip-views", action="store_true", help="only the streams at --fps")
    parser.add_argument("--modes", nargs="+", choices=("realtime", "lossless"), default=["realtime", "lossless"],
                        help="the sessions the --fps stream goes into (default both)")
    parser.add_argument("--json", help="also write the figures here")
    args = parser.parse_args()
    frame_set = open_frames(args.data, "auto", args.frames, 1, args.scale)
    frames = [frame_to_proto(frame_set.load(p)) for p in frame_set.selection.streamed]
    request = pb.CreateSessionRequest(preset=args.preset)
    out: dict[str, list] = {"views": [], "realtime": []}
    with tempfile.TemporaryDirectory() as tmp:
        record_dir = Path(tmp)
        runs = [] if args.skip_views else [("off", ("--view-seconds", "0")), ("recorded", ()),
                                           ("foxglove", ("--foxglove-port", "0"))] * args.repeat
        for number, (name, flags) in enumerate(runs):
            row = views_run(name, frames, request, record_dir / str(number), *flags)
            out["views"].append(asdict(row))
            print(row, flush=True)
        for mode in args.modes:
            streamed = pb.CreateSessionRequest(preset=args.preset, realtime=mode == "realtime")
            row = stream_run(mode, frames, streamed, args.fps, record_dir)
            out["realtime"].append(asdict(row))
            print(row, flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
