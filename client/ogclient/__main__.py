"""``ogclient``: stream datasets or recordings into an ogserver, render, snapshot, restore, score."""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import grpc

from ogclient import commands, corrections
from ogclient.connection import DEFAULT_SERVER, ClientError, Transport, connect, describe
from ogmapping.cli.options import add_bag_arguments, add_config_arguments, add_dataset_arguments
from ogmapping.datasets import FORMATS

EPILOG = """\
typical session:
  ogclient --server 127.0.0.1:50051 stream --data ../shared/data/7scenes-redkitchen --frames 0:100 \\
      --scale 0.25 --session-out out/kitchen.json
  ogclient stream --data ../shared/data/replica-room0 --scale 0.25 --session-out out/replica.json
  ogclient stream --bag robot.bag --scale 0.5 --close        # ROS 1/2 bag: topics, TF, see docs/robots.md
  ogclient eval --session out/kitchen.json --data ../shared/data/7scenes-redkitchen --frames 0:100 --scale 0.25
  ogclient render --session out/kitchen.json --data ../shared/data/7scenes-redkitchen --scale 0.25 --position 55
  ogclient snapshot --session out/kitchen.json --out out/kitchen.safetensors
  ogclient correct-poses --session out/kitchen.json slam-corrected.tum   # a loop closure: poses already mapped
  ogclient stream --bag robot.bag --corrected-topic /slam/path   # ... or the bag's SLAM path, once all are mapped
  ogclient close --session out/kitchen.json
  ogclient replay recordings/<session>.mcap --close
  ogclient repair-recording recordings/<session>.mcap repaired.mcap   # after a server crash
  ogclient trajectory recordings/<session>.mcap --out refined.tum   # poses.refine; --client: the sent poses
  ogclient view out/kitchen.safetensors --open      # the map as Gaussians in the browser (also a recording)

Session commands read the credentials file written by create/stream/replay/restore (--session-out,
default out/session.json). --server defaults to $OGMAP_SERVER or 127.0.0.1:50051. A server with API keys
wants one for create/stream/replay/restore/list: --api-key-file FILE or $OGMAP_API_KEY. Exit status:
0 ok, 1 the server refused a call (or rejected frames), 2 usage error or server unreachable."""


DEFAULT_SESSION_FILE = "out/session.json"  # under out/ (git-ignored): it holds the session's token


def add_session_out(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--session-out", default=DEFAULT_SESSION_FILE,
                        help=f"where to write the new session's id and token (default {DEFAULT_SESSION_FILE})")
    parser.add_argument("--label", default="", help="free text shown by `ogclient list`")


def add_realtime(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--realtime", action="store_true",
                        help="a realtime session: frames that arrive while the mapper is busy are skipped (recorded "
                             "and acknowledged as skipped, never mapped) instead of holding the sender back")


def add_trajectory(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--trajectory", metavar="FILE",
                        help="a session that refines poses (poses.refine): write the refined pose of each mapped "
                             "frame to FILE as a TUM trajectory")


def add_session(parser: argparse.ArgumentParser, required: bool = True) -> None:
    parser.add_argument("--session", required=required, metavar="FILE",
                        help="credentials file written by create/stream/replay/restore")


def parser() -> argparse.ArgumentParser:
    root = argparse.ArgumentParser(prog="ogclient", description=__doc__, epilog=EPILOG,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    root.add_argument("--server", default=DEFAULT_SERVER, help=f"HOST:PORT of the ogserver (default {DEFAULT_SERVER})")
    root.add_argument("--timeout", type=float, default=10.0, help="seconds to wait for the server to answer (10)")
    root.add_argument("--tls", action="store_true", help="connect over TLS, trusting the system's CAs")
    root.add_argument("--tls-ca", metavar="PEM", help="connect over TLS, trusting this CA")
    root.add_argument("--tls-cert", metavar="PEM", help="client certificate, for a server that requires one")
    root.add_argument("--tls-key", metavar="PEM", help="the client certificate's private key")
    root.add_argument("--api-key-file", metavar="FILE",
                      help="file holding the API key the server gave you (default: $OGMAP_API_KEY)")
    sub = root.add_subparsers(dest="command", required=True, metavar="COMMAND")

    create = sub.add_parser("create", help="open an empty session", description="Open an empty mapping session.")
    add_config_arguments(create)
    add_realtime(create)
    add_session_out(create)
    create.set_defaults(handler=commands.create)

    stream = sub.add_parser(
        "stream", help="stream a dataset into a (new) session",
        description="Stream the selected frames (the same selection as `ogmap run`: positions with "
        "index % 10 == 5 are held out and never streamed) with a progress bar of live acks. Creates a "
        "session unless --session names one. Rejected frames are reported and make the exit status 1.",
    )
    add_dataset_arguments(stream)
    add_config_arguments(stream)
    add_realtime(stream)
    stream.add_argument("--fps", type=float, default=0.0,
                        help="send at this rate, like a sensor (default 0: as fast as the server takes them)")
    add_session(stream, required=False)
    add_session_out(stream)
    stream.add_argument("--color-encoding", choices=sorted(commands.COLOR_CHOICES), default="png",
                        help="how colour travels (default png: lossless for 8-bit data)")
    stream.add_argument("--depth-encoding", choices=sorted(commands.DEPTH_CHOICES), default="png16",
                        help="how depth travels (default png16)")
    stream.add_argument("--depth-scale", type=float, default=1000.0, help="PNG16 units per metre (default 1000 = mm)")
    stream.add_argument("--jpeg-quality", type=int, default=95, help="for --color-encoding jpeg (default 95)")
    stream.add_argument("--resume", action="store_true",
                        help="with --session: go on where the session stands (after a dropped connection or a "
                             "server crash): ask it for the last frame it has taken and stream only the frames "
                             "after it")
    stream.add_argument("--retries", type=int, default=8,
                        help="a stream cut by UNAVAILABLE (the server or its node failed) is resumed by itself: wait "
                             "(0.5 s, doubling, up to 15 s), ask GetStats for the last frame the session holds and "
                             "stream the frames after it; at most this many UNAVAILABLE answers with no frame "
                             "acknowledged in between (default 8; 0: stop at the first)")
    stream.add_argument("--close", action="store_true", help="close the session when done")
    stream.add_argument("--quiet", action="store_true", help="no progress bar")
    add_trajectory(stream)
    corrected = stream.add_mutually_exclusive_group()
    corrected.add_argument("--corrected-trajectory", metavar="FILE",
                           help="a TUM trajectory of corrected poses (a SLAM system's after a loop closure, e.g. for "
                                "a --bag): once every frame is mapped, the poses of the frames this stream mapped are "
                                "sent as pose corrections (matched by timestamp, else index; see correct-poses)")
    corrected.add_argument("--corrected-topic", metavar="TOPIC",
                           help="with --bag: the same from a topic of the bag, read before streaming: nav_msgs/Path "
                                "(its last message, each pose stamped) or PoseStamped, PoseWithCovarianceStamped, "
                                "Odometry (a corrected pose a message), in the frames' world and mounted by TF as "
                                "--pose-topic's poses are (the body: --body-frame, else Odometry's child frame, else "
                                "the pose source's); never taken as the pose source")
    stream.set_defaults(handler=commands.stream)

    replay = sub.add_parser(
        "replay", help="stream a session recording (.mcap) into a new session",
        description="Create a session with the recorded preset and resolved config and stream the recorded "
        "frames, unchanged, as fast as the server takes them (or --realtime at the recorded rate).",
    )
    replay.add_argument("recording", help="an .mcap file from the server's record dir (crashed ones work too)")
    replay.add_argument("--realtime", action="store_true", help="keep the recorded frame timing")
    add_session_out(replay)
    replay.add_argument("--close", action="store_true", help="close the session when done")
    replay.add_argument("--quiet", action="store_true", help="no progress bar")
    add_trajectory(replay)
    replay.set_defaults(handler=commands.replay)

    repair = sub.add_parser(
        "repair-recording", help="give a recording cut by a crash its summary and index (no server needed)",
        description="Copy every message of a recording that was never closed (the server crashed or was killed) "
        "into a new file with the summary and index a clean close appends, so any MCAP tool opens it. A file "
        "damaged before its end (not just cut) is refused.",
    )
    repair.add_argument("recording", help="the .mcap file to read")
    repair.add_argument("out", help="the .mcap file to write")
    repair.set_defaults(handler=commands.repair_recording, offline=True)

    trajectory = sub.add_parser(
        "trajectory", help="write a recording's refined (or the client's) trajectory in TUM format (no server needed)",
        description="Write the refined camera poses a recording holds (a session with poses.refine acknowledges "
        "each mapped frame with its refined pose), or with --client the poses the client sent, as a TUM trajectory: "
        "`timestamp tx ty tz qx qy qz qw` a line, keyed by the frame's timestamp, else its index.",
    )
    trajectory.add_argument("recording", help="an .mcap file from the server's record dir (crashed ones work too)")
    trajectory.add_argument("--out", required=True, help="the TUM file to write")
    trajectory.add_argument("--client", action="store_true", help="the client's poses, not the refined ones")
    trajectory.set_defaults(handler=commands.trajectory, offline=True)

    view = sub.add_parser(
        "view", help="show a snapshot's or a recording's map as Gaussians in the browser (no running server needed)",
        description="Serve the web view of a snapshot (.safetensors), or of the map at the end of a recording "
        "(.mcap: its final snapshot beside it, else its frames mapped here as a replay would), on 127.0.0.1 "
        "until Ctrl-C. The page is served by a local `ogserver view` started for it as a child process and "
        "stopped with this command. Prints the page's URL, a one-time token in its query; append #pose=... "
        "(docs/service.md) for a fixed camera. A map that cannot be read: one line, exit status 2.")
    view.add_argument("map", help="a snapshot (.safetensors) or a recording (.mcap)")
    view.add_argument("--port", type=int, default=0, help="port on 127.0.0.1 (default: any free one)")
    view.add_argument("--device", default="auto", help="where to load and decode the map: auto, cpu, cuda")
    view.add_argument("--open", action="store_true", help="open the page in the default browser")
    view.add_argument("--quiet", action="store_true", help="no progress bar while a recording's frames are mapped")
    view.set_defaults(handler=commands.view, offline=True)

    render = sub.add_parser(
        "render", help="render a pose to PNGs",
        description="Render the map from a dataset frame's pose (--data or --bag, --position) or from a pose file "
        "and intrinsics; writes color.png, depth.png (16-bit mm) and preview.png into --out.",
    )
    add_session(render)
    source = render.add_mutually_exclusive_group()
    source.add_argument("--data", help="dataset folder (or 'synthetic') to take pose and intrinsics from")
    source.add_argument("--bag", metavar="PATH", help="a ROS bag to take them from (see docs/robots.md)")
    render.add_argument("--format", default="auto", choices=FORMATS, help="dataset layout (default: detect)")
    render.add_argument("--scale", type=float, default=1.0, help="image scale (default 1)")
    render.add_argument("--position", type=int, help="frame position in the dataset")
    render.add_argument("--pose", help="text file with a 4x4 camera-to-world matrix")
    render.add_argument("--intrinsics", help="fx,fy,cx,cy in pixels (with --pose)")
    render.add_argument("--size", help="WIDTHxHEIGHT (with --pose)")
    at = render.add_mutually_exclusive_group()
    at.add_argument("--sequence", type=int, help="the pose is the client's at the time of this frame (its FrameAck "
                    "sequence): with poses.refine the server moves it as the mapped keyframe nearest that frame "
                    "was moved (default with --position: the frame's own timestamp, where it has one)")
    at.add_argument("--timestamp", type=float, help="as --sequence, by a frame's timestamp (seconds)")
    render.add_argument("--out", default="renders", help="output folder (default renders/)")
    add_bag_arguments(render)
    render.set_defaults(handler=commands.render)

    snapshot = sub.add_parser("snapshot", help="save the map (safetensors)", description="Download the map.")
    add_session(snapshot)
    snapshot.add_argument("--out", required=True, help="file to write, e.g. map.safetensors")
    snapshot.set_defaults(handler=commands.snapshot)

    restore = sub.add_parser("restore", help="upload a snapshot into a new session",
                             description="Create a session from a snapshot; mapping can continue in it.")
    restore.add_argument("snapshot", help="a snapshot written by `ogclient snapshot` or `ogmap run`")
    add_session_out(restore)
    restore.set_defaults(handler=commands.restore)

    stats = sub.add_parser("stats", help="print a session's statistics (JSON)", description="Session statistics.")
    add_session(stats)
    stats.set_defaults(handler=commands.stats)

    evaluate = sub.add_parser(
        "eval", help="score a session on streamed and held-out frames",
        description="Render every streamed and held-out pose of the selection through the server and score "
        "it like `ogmap run` (PSNR, SSIM, MS-SSIM, LPIPS, depth L1 in cm); pass the same dataset flags used to stream.",
    )
    add_session(evaluate)
    add_dataset_arguments(evaluate)
    evaluate.add_argument("--out", help="folder for results.json and side-by-side previews")
    evaluate.add_argument("--quiet", action="store_true", help="no progress bars")
    evaluate.set_defaults(handler=commands.evaluate_command)

    listing = sub.add_parser("list", help="list your sessions on the server",
                             description="List the sessions you created (on an open server: every session).")
    listing.set_defaults(handler=commands.list_sessions)

    correct = sub.add_parser(
        "correct-poses", help="send corrected poses of mapped frames (a SLAM loop closure) to a session",
        description="Send a corrected trajectory (TUM: timestamp tx ty tz qx qy qz qw, camera-to-world) for frames "
                    "the session already mapped. Each keyframe's anchors move rigidly with its correction and it is "
                    "optimised again; lines naming mapped frames that are not keyframes move nothing. Sent in batches, "
                    "each applied whole or not at all: a refused batch (an unknown frame, a pose that is not rigid, a "
                    "jump beyond the server's bounds) is named and leaves the batches before it applied.")
    add_session(correct)
    correct.add_argument("trajectory", help="TUM trajectory file of corrected camera-to-world poses")
    correct.add_argument("--keys", choices=("timestamp", "sequence"), default="timestamp",
                         help="what the file's first column is: the frames' timestamps as they were sent (default), "
                              "or their FrameAck.sequence numbers")
    correct.add_argument("--batch", type=int, default=corrections.DEFAULT_BATCH,
                         help=f"poses a call (default {corrections.DEFAULT_BATCH}; the server's "
                              "limits.max_pose_corrections caps it)")
    correct.set_defaults(handler=commands.correct_poses)

    close = sub.add_parser("close", help="close a session (finishes its recording)", description="Close a session.")
    add_session(close)
    close.set_defaults(handler=commands.close)
    return root


def transport(args: argparse.Namespace) -> Transport:
    if args.api_key_file:
        try:
            api_key = Path(args.api_key_file).read_text().strip()
        except OSError as error:
            raise ClientError(f"cannot read {args.api_key_file}: {error.strerror}") from None
    else:
        api_key = os.environ.get("OGMAP_API_KEY", "")
    return Transport(args.tls, args.tls_ca or "", args.tls_cert or "", args.tls_key or "", api_key)


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    try:
        if getattr(args, "offline", False):
            return args.handler(args)
        channel, stub = connect(args.server, args.timeout, transport(args))
        with channel:
            return args.handler(commands.Context(stub, args.server), args)
    except ClientError as error:
        print(f"ogclient: {error}", file=sys.stderr)
        return 2
    except grpc.RpcError as error:
        print(f"ogclient: call failed: {describe(error)}", file=sys.stderr)
        return 1
    except (ValueError, OSError) as error:
        print(f"ogclient: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
