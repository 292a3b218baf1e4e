"""``python -m ogclient.demo --out out/demo`` (what ``make demo`` runs): the service end to end.

Starts an ogserver subprocess on a free local port (its web view too, the URL printed), streams the
synthetic scene into a session, scores streamed and held-out views through the server like ``ogmap
run``, and leaves side-by-side renders, a snapshot, results.json and the session's MCAP recording
under --out. The server is stopped (SIGTERM) whatever happens; with --keep only at Ctrl-C, after the
results, so the watch link, ``ogclient view`` and ``ogclient replay`` it prints can be tried first.

The start-up wait follows the server's warm-up: a first start compiles the kernels (minutes on a busy
machine) and logs each stage; the demo gives up only after --start-timeout seconds without a new line.
"""

from __future__ import annotations

import argparse
import json
import shutil
import signal
import sys
import time
from pathlib import Path

import grpc
from ogapi.v1 import mapping_pb2 as pb
from ogapi.v1 import mapping_pb2_grpc as pb_grpc

from ogclient.connection import ClientError, SessionRef, connect, describe
from ogclient.evaluation import evaluate, snapshot_bytes
from ogclient.local_server import LocalServer, StartTimeout
from ogclient.messages import frame_to_proto, restore_chunks
from ogclient.shell import command
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
    p.add_argument("--start-timeout", type=float, default=300.0, metavar="SECONDS",
                   help="give up on the server's start after this long without a new line in its log (300; a "
                   "first start logs each warm-up stage as it compiles the kernels)")
    p.add_argument("--keep", action="store_true",
                   help="keep the server up after mapping, until Ctrl-C: the session's map stays on its watch "
                   "link and recordings can be replayed into it (make demo KEEP=1)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def map_gaussians(snapshot: bytes) -> int:
    """The whole map's Gaussians, as ``ogmap export`` writes them and the web view draws them (every
    anchor's, decoded from the mapped cameras' centroid; those a view culls included)."""
    from ogmapping.mapper import Mapper
    from ogmapping.persist.export import default_viewpoint

    mapper = Mapper.restore(snapshot, "cpu")
    return int(mapper.decode_at(default_viewpoint(mapper).center).means.shape[0])


def show_warm_up(line: str) -> None:
    """The server's warm-up lines, while the demo waits for them, without the log's time and level."""
    if "warm" in line:
        print(f"  {line.split(': ', 1)[-1]}", flush=True)


def keep_serving(server: LocalServer) -> None:
    """Wait for Ctrl-C or SIGTERM (then the server stops as usual), or for the server to exit by itself."""
    previous = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        while server.process is not None and server.process.poll() is None:
            time.sleep(0.5)
    except KeyboardInterrupt:
        print("\nstopping the server", flush=True)
    finally:
        signal.signal(signal.SIGTERM, previous)


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
    print(f"starting ogserver (log {out / 'server.log'})", flush=True)
    with LocalServer(record_dir, "--device", args.device, "--web-port", str(args.web_port),
                     log_path=out / "server.log", start_timeout=args.start_timeout,
                     progress=show_warm_up) as server:
        channel, stub = connect(server.address, timeout=60)
        with channel:
            print(server.ready_line)
            request = pb.CreateSessionRequest(preset=args.preset, overrides=overrides, label="demo")
            credentials = stub.CreateSession(request)
            session = SessionRef.from_credentials(credentials)
            session.save(out / "session.json", server.address)
            print(f"session {session.session_id}: preset {args.preset}, "
                  + ", ".join(f"{k}={v}" for k, v in overrides.items()))
            print(f"watch it map, as Gaussians in the browser: {server.web_url}map/{session.session_id}"
                  + ("" if args.keep else " (while the demo runs; `make demo KEEP=1` keeps the map up afterwards)"))
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
            kept = restore_kept(stub, snapshot, out, server.address) if args.keep else None
        recording = record_dir / closed.recording
        results["eval_seconds"] = eval_seconds
        results["map_gaussians"] = map_gaussians(snapshot.read_bytes())
        (out / "results.json").write_text(json.dumps(results, indent=2))
        report(results, out, snapshot, recording)
        ogclient = command("ogclient")
        print(f"the map in the browser, afterwards: {ogclient} view {snapshot} --open")
        if kept is None:
            print(f"replay the recording into a new session: `{command('ogserver')}` in another shell, then "
                  f"`{ogclient} replay {recording}`; or `make demo KEEP=1`, which keeps its server up and prints "
                  "the command with its address")
            return 0
        print(f"the server stays up (Ctrl-C stops it; it records to {record_dir}):")
        print(f"  the map, restored into session {kept.session_id}: {server.web_url}map/{kept.session_id}")
        print(f"  replay the recording into a new session there: {ogclient} --server {server.address} replay "
              f"{recording} --session-out {out / 'replay-session.json'}")
        keep_serving(server)
    return 0


def restore_kept(stub: pb_grpc.MappingStub, snapshot: Path, out: Path, address: str) -> SessionRef:
    """The demo's final map in a new session of the kept server (the mapping one is closed, its recording
    finished), so the web view keeps showing it; its credentials in out/kept-session.json."""
    session = SessionRef.from_credentials(stub.RestoreSession(restore_chunks(snapshot.read_bytes(), "demo (restored)")))
    session.save(out / "kept-session.json", address)
    return session


def report(results: dict, out: Path, snapshot: Path, recording: Path) -> None:
    """Speed, quality and where everything went."""
    print(f"speed: processing {results['processing_fps']:.2f} frames/s on {results['device']}, "
          f"render {fmt(results['render_fps'], 1)} frames/s through the server")
    print("quality          PSNR dB  PSNR affine-fit dB   SSIM  MS-SSIM  LPIPS   depth L1 cm")
    for split, name in (("streamed", "streamed"), ("heldout", "held-out")):
        scores = results[split]
        print(f"  {name:9s} ({scores['frames']:2d})  {fmt(scores['psnr'], 2):>6s}  "
              f"{fmt(scores['psnr_affine'], 2):>18s}  {fmt(scores['ssim'], 3):>6s}  {fmt(scores['ms_ssim'], 3):>7s}  "
              f"{fmt(scores['lpips'], 3):>6s}  {fmt(scores['depth_l1_cm'], 2):>8s}")
    print("  (PSNR: the render as it is; PSNR affine-fit: after each frame's own gain and offset, fitted to it)")
    print(f"map: {results['anchors']} anchors, {results['map_gaussians']} Gaussians (what `ogmap export` writes "
          f"and the web view draws; {results['gaussians']} of them drawn in the last keyframe's view), "
          f"snapshot {snapshot} ({results['snapshot_bytes']} bytes)")
    renders = sorted(out.glob("*_0*.png"))
    print(f"renders (render | truth, depth below): {', '.join(str(p) for p in renders)}")
    print(f"recording: {recording} ({recording.stat().st_size} bytes; opens in Foxglove)")
    print(f"results: {out / 'results.json'}")


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        return run(args)
    except StartTimeout as error:
        print(f"demo failed: {error}\nthe server was still starting {error.waited:.0f} s in (a first start compiles "
              f"the kernels; the compiled ones are kept): run `make demo` again, or wait longer without a new log "
              f"line with `make demo DEMO_ARGS='--start-timeout {2 * error.quiet:.0f}'`", file=sys.stderr)
        return 1
    except grpc.RpcError as error:
        print(f"demo failed: {describe(error)}", file=sys.stderr)
        return 1
    except (ClientError, RuntimeError, ValueError) as error:
        print(f"demo failed: {error}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
