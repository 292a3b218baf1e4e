"""``python -m ogclient.demo --out out/demo`` (what ``make demo`` runs): the service end to end.

Starts an ogserver subprocess on a free local port (its web view too, the URL printed), streams the
synthetic scene into a session, scores streamed and held-out views through the server like ``ogmap
run``, and leaves side-by-side renders, a snapshot, results.json and the session's MCAP recording
under --out. The server is stopped (SIGTERM) whatever happens.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

import grpc
from ogapi.v1 import mapping_pb2 as pb

from ogclient.connection import ClientError, SessionRef, connect, describe
from ogclient.evaluation import evaluate, snapshot_bytes
from ogclient.local_server import LocalServer
from ogclient.messages import frame_to_proto
from ogclient.streaming import stream_frames
from ogmapping.config import parse_override_args, resolve
from ogmapping.quality.evaluation import open_frames

# Sized for a 2-core CPU: 160x120 images, 40 frames (36 streamed, 4 held out), 40 iterations on the
# first keyframe and 8 on each later one (window keyframes stay full size at this width:
# keyframes.window_min_width): about 25 seconds on an idle machine. With a GPU, raise --scale and
# the iterations.
DEFAULT_FRAMES = "0:40"
DEFAULT_SCALE = 0.5
DEFAULT_PRESET = "sparse-fast"
DEFAULT_OVERRIDES = {"keyframes.first_iterations": "40", "keyframes.iterations": "8"}


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m ogclient.demo", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    p.add_argument("--frames", default=DEFAULT_FRAMES, help=f"synthetic positions START:END ({DEFAULT_FRAMES})")
    p.add_argument("--scale", type=float, default=DEFAULT_SCALE, help=f"of 320x240 ({DEFAULT_SCALE})")
    p.add_argument("--preset", default=DEFAULT_PRESET, help=f"engine preset ({DEFAULT_PRESET})")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="config override on top of the demo's "
                   + ", ".join(f"{k}={v}" for k, v in DEFAULT_OVERRIDES.items()))
    p.add_argument("--device", default="auto", help="server device: auto (GPU if any, else CPU), cpu, cuda")
    p.add_argument("--web-port", type=int, default=0,
                   help="the server's web view port on 127.0.0.1 (default 0: any free one, printed)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def fmt(value: float | None, digits: int) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def run(args: argparse.Namespace) -> int:
    out = Path(args.out)
    record_dir = out / "recordings"
    shutil.rmtree(record_dir, ignore_errors=True)
    overrides = {**DEFAULT_OVERRIDES, **parse_override_args(args.overrides)}
    resolve(args.preset, overrides=overrides)  # a bad key or value fails here, before a server starts
    frames = open_frames("synthetic", "synthetic", args.frames, 1, args.scale)
    selection = frames.selection
    sample = frames.load(selection.streamed[0]).color_intrinsics

    print("OG-Mapping service demo", flush=True)
    with LocalServer(record_dir, "--device", args.device, "--web-port", str(args.web_port),
                     log_path=out / "server.log") as server:
        channel, stub = connect(server.address, timeout=60)
        with channel:
            print(f"{server.ready_line}; log {out / 'server.log'}")
            request = pb.CreateSessionRequest(preset=args.preset, overrides=overrides, label="demo")
            credentials = stub.CreateSession(request)
            session = SessionRef.from_credentials(credentials)
            session.save(out / "session.json", server.address)
            print(f"session {session.session_id}: preset {args.preset}, "
                  + ", ".join(f"{k}={v}" for k, v in overrides.items()))
            print(f"watch it map, as Gaussians in the browser: {server.web_url}map/{session.session_id}")
            print(f"streaming {len(selection.streamed)} synthetic frames at {sample.width}x{sample.height} "
                  f"({len(selection.heldout)} held out)", flush=True)
            messages = (frame_to_proto(frames.load(position)) for position in selection.streamed)
            result = stream_frames(stub, session, messages, total=len(selection.streamed), progress=not args.quiet)
            if result.rejected:
                raise ClientError(f"{len(result.rejected)} frames were rejected")
            print(result.summary())
            tic = time.perf_counter()
            results = evaluate(stub, session, frames, out=out, progress=not args.quiet)
            eval_seconds = time.perf_counter() - tic
            snapshot = out / "map.safetensors"
            snapshot.write_bytes(snapshot_bytes(stub, session))
            closed = stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id),
                                       metadata=session.metadata())
    recording = record_dir / closed.recording
    results["eval_seconds"] = eval_seconds
    (out / "results.json").write_text(json.dumps(results, indent=2))
    print(f"speed: processing {results['processing_fps']:.2f} frames/s on {results['device']}, "
          f"render {fmt(results['render_fps'], 1)} frames/s through the server")
    print("quality          PSNR dB   SSIM  MS-SSIM  LPIPS   depth L1 cm")
    for split, name in (("streamed", "streamed"), ("heldout", "held-out")):
        scores = results[split]
        print(f"  {name:9s} ({scores['frames']:2d})  {fmt(scores['psnr'], 2):>6s}  {fmt(scores['ssim'], 3):>6s}  "
              f"{fmt(scores['ms_ssim'], 3):>7s}  {fmt(scores['lpips'], 3):>6s}  {fmt(scores['depth_l1_cm'], 2):>8s}")
    print(f"map: {results['anchors']} anchors, {results['gaussians']} Gaussians, "
          f"snapshot {snapshot} ({results['snapshot_bytes']} bytes)")
    renders = sorted(out.glob("*_0*.png"))
    print(f"renders (render | truth, depth below): {', '.join(str(p) for p in renders)}")
    print(f"recording: {recording} ({recording.stat().st_size} bytes; opens in Foxglove, "
          f"replay with `ogclient replay {recording}`)")
    print(f"results: {out / 'results.json'}")
    print(f"the map in the browser, afterwards: ogclient view {snapshot} --open")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        return run(args)
    except grpc.RpcError as error:
        print(f"demo failed: {describe(error)}", file=sys.stderr)
        return 1
    except (ClientError, RuntimeError, ValueError) as error:
        print(f"demo failed: {error}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
