"""What each ``ogclient`` subcommand does, given parsed arguments, a stub and the server address."""

from __future__ import annotations

import argparse
import json
import webbrowser
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from ogapi import recording
from ogapi.convert import FrameEncoding, matrix_to_list
from ogapi.images import decode_color, decode_depth
from ogapi.v1 import mapping_pb2 as pb
from ogapi.v1 import mapping_pb2_grpc as pb_grpc

from ogclient import corrections, viewing
from ogclient import replay as replaying
from ogclient import trajectory as trajectories
from ogclient.connection import ClientError, SessionRef
from ogclient.evaluation import evaluate, snapshot_bytes
from ogclient.messages import frame_to_proto, intrinsics_to_proto, restore_chunks
from ogclient.resuming import Backoff, stream_resuming
from ogclient.streaming import StreamResult, paced, stream_frames
from ogmapping.cli.options import dataset_source, open_frame_set, parse_intrinsics
from ogmapping.config import load_file, parse_override_args, resolve
from ogmapping.frames.camera import validate_pose
from ogmapping.frames.trajectory import Trajectory, read_tum
from ogmapping.quality.evaluation import open_frames

COLOR_CHOICES = {"png": pb.COLOR_PNG, "jpeg": pb.COLOR_JPEG, "raw": pb.COLOR_RAW_RGB8}
DEPTH_CHOICES = {"png16": pb.DEPTH_PNG16, "raw": pb.DEPTH_RAW_F32}


@dataclass
class Context:
    stub: pb_grpc.MappingStub
    server: str


def overrides_from_args(args: argparse.Namespace) -> dict[str, str]:
    """--config FILE then --set KEY=VALUE, as the text values CreateSession takes.

    Resolved here first, as the server will resolve them: a bad key or value fails before any call,
    with the message the server would give.
    """
    overrides = load_file(args.config) if args.config else {}
    overrides.update(parse_override_args(args.overrides))
    resolve(args.preset, overrides=overrides)
    return {key: str(value).lower() if isinstance(value, bool) else str(value) for key, value in overrides.items()}


def announce(credentials: pb.SessionCredentials, args: argparse.Namespace, server: str) -> SessionRef:
    session = SessionRef.from_credentials(credentials)
    session.save(args.session_out, server)
    print(f"session {session.session_id} on {credentials.device}; credentials in {args.session_out}; "
          f"server records to {credentials.recording} in its record dir", flush=True)
    return session


def close_if_asked(ctx: Context, session: SessionRef, args: argparse.Namespace) -> None:
    if getattr(args, "close", False):
        response = ctx.stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id),
                                         metadata=session.metadata())
        print(f"closed; recording {response.recording} in the server's record dir")


def create_request(args: argparse.Namespace) -> pb.CreateSessionRequest:
    return pb.CreateSessionRequest(preset=args.preset, overrides=overrides_from_args(args), label=args.label,
                                   realtime=args.realtime)


def create(ctx: Context, args: argparse.Namespace) -> int:
    announce(ctx.stub.CreateSession(create_request(args)), args, ctx.server)
    return 0


def resumed_positions(ctx: Context, session: SessionRef, positions: list[int]) -> list[int]:
    """The positions after the last frame the session has taken (GetStats' last_sequence and its
    Frame.index, which ogclient sets to the position): what a stream that goes on sends, so no frame
    is mapped twice. A session that has taken none gets them all."""
    stats = ctx.stub.GetStats(pb.GetStatsRequest(session_id=session.session_id), metadata=session.metadata())
    if not stats.last_sequence:
        print("resuming: the session has taken no frame yet; streaming all of them", flush=True)
        return positions
    remaining = [position for position in positions if position > stats.last_index]
    print(f"resuming: the session has taken {stats.last_sequence} frames, the last at position {stats.last_index}; "
          f"streaming the {len(remaining)} selected after it", flush=True)
    return remaining


def stream(ctx: Context, args: argparse.Namespace) -> int:
    frame_set = open_frame_set(args)  # a bag reads --corrected-topic as it opens
    corrected = read_tum(args.corrected_trajectory) if args.corrected_trajectory else frame_set.source.corrected
    if args.resume and not args.session:
        raise ClientError("--resume goes on with an existing session: name its credentials with --session FILE")
    if args.fps < 0:
        raise ClientError(f"--fps must be >= 0 (got {args.fps:g})")
    if args.retries < 0:
        raise ClientError(f"--retries must be >= 0 (got {args.retries})")
    for line in frame_set.source.report():
        print(f"{frame_set.source.name}: {line}", flush=True)
    if args.session:
        if args.realtime:
            raise ClientError("--realtime is chosen when the session is created; drop --session or --realtime")
        session = SessionRef.load(args.session)
    else:
        session = announce(ctx.stub.CreateSession(create_request(args)), args, ctx.server)
    encoding = FrameEncoding(color=COLOR_CHOICES[args.color_encoding], depth=DEPTH_CHOICES[args.depth_encoding],
                             depth_scale=args.depth_scale, jpeg_quality=args.jpeg_quality)
    positions = list(frame_set.selection.streamed)
    if args.resume:
        positions = resumed_positions(ctx, session, positions)

    keys: dict[int, float] = {}  # Frame.index -> the frame's key in a TUM file

    def load(position: int) -> pb.Frame:
        message = frame_to_proto(frame_set.load(position), encoding)
        keys[message.index] = trajectories.frame_key(message)
        return message

    def after(last_index: int | None) -> Iterator[pb.Frame]:
        """The selected frames after the last one the session holds (ogclient sets Frame.index to the position)."""
        chosen = [position for position in positions if last_index is None or position > last_index]
        return paced((load(position) for position in chosen), args.fps)

    result = stream_resuming(ctx.stub, session, after, total=len(positions), progress=not args.quiet,
                             backoff=Backoff(retries=args.retries))
    print(result.summary())
    correct_streamed(ctx, session, corrected, keys, result)
    close_if_asked(ctx, session, args)
    write_refined(args.trajectory, keys, result)
    return 1 if result.rejected else 0


def correct_streamed(ctx: Context, session: SessionRef, trajectory: Trajectory | None, keys: dict[int, float],
                     result: StreamResult) -> None:
    """--corrected-trajectory or --corrected-topic: once every frame is mapped, the trajectory's poses of the
    frames this stream mapped (matched by key: timestamp, else index) sent as pose corrections; its other poses
    are left out."""
    if trajectory is None:
        return
    name, count = trajectory.name, len(trajectory.keys)
    poses = corrections.for_mapped(trajectory, keys, result.acks)
    if not poses:
        raise ClientError(f"{name}: none of its {count} poses is of a frame this stream mapped")
    sent = corrections.send(ctx.stub, session, poses, corrections.DEFAULT_BATCH)
    print(f"{name}: {len(poses)} of its {count} poses are of frames mapped here; {sent.summary()}")


def write_refined(path: str | None, keys: dict[int, float], result: StreamResult) -> None:
    """--trajectory: the refined pose of every frame acknowledged with one, in TUM format."""
    if not path:
        return
    poses = trajectories.refined_poses(keys, result.acks)
    if not poses.keys:
        raise ClientError(f"no frame's ack carries a refined pose (the session does not refine poses: "
                          f"poses.refine); {path} was not written")
    poses.write(path, "refined camera-to-world poses of the frames the session mapped")
    print(f"wrote {path}: {len(poses.keys)} refined poses")


def replay(ctx: Context, args: argparse.Namespace) -> int:
    recorded = recording.load(args.recording)
    if not recorded.frames:
        raise ClientError(f"{args.recording} holds no frames")
    if recorded.config is not None and recorded.config.restored_from_sha256:
        print("note: the recorded session started from a restored snapshot; the replay starts from an empty map")
    if recorded.config is not None and recorded.config.realtime:
        skipped = sum(ack.skipped for ack in recorded.acks)
        print(f"note: the recorded session was realtime and skipped {skipped} of its frames; the replay is lossless "
              "and maps every recorded frame")
    credentials = ctx.stub.CreateSession(replaying.session_request(recorded.config, args.label))
    session = announce(credentials, args, ctx.server)
    result = StreamResult()
    # Each recorded batch of pose corrections once the frames before it are mapped, as the recorded session took it.
    for segment in corrections.segments(recorded):
        if segment.end > segment.start:
            stream_frames(ctx.stub, session, replaying.frames(recorded, args.realtime, segment.start, segment.end),
                          total=segment.end - segment.start, progress=not args.quiet, result=result)
        if segment.corrections is not None:
            sent = corrections.send(ctx.stub, session, list(segment.corrections.poses), len(segment.corrections.poses))
            print(f"after frame {segment.end}: {sent.summary()}")
    print(result.summary())
    close_if_asked(ctx, session, args)
    write_refined(args.trajectory, {frame.index: trajectories.frame_key(frame) for _, frame in recorded.frames},
                  result)
    return 1 if result.rejected else 0


def correct_poses(ctx: Context, args: argparse.Namespace) -> int:
    """A corrected trajectory (TUM) to a session, in batches."""
    if args.batch < 1:
        raise ClientError("--batch must be 1 or more")
    session = SessionRef.load(args.session)
    poses = corrections.entries(read_tum(args.trajectory), args.keys)
    sent = corrections.send(ctx.stub, session, poses, args.batch)
    print(sent.summary())
    return 0


def trajectory(args: argparse.Namespace) -> int:
    """Needs no server: a recording's refined trajectory (or with --client the client's), in TUM format."""
    poses = trajectories.from_recording(recording.load(args.recording), args.recording, args.client)
    whose = "client's" if args.client else "refined"
    poses.write(args.out, f"the {whose} camera-to-world poses recorded in {Path(args.recording).name}")
    print(f"wrote {args.out}: {len(poses.keys)} {whose} poses")
    return 0


def repair_recording(args: argparse.Namespace) -> int:
    """Needs no server: rewrites a recording cut by a crash with the summary and index a clean close appends."""
    if Path(args.out).resolve() == Path(args.recording).resolve():
        raise ClientError("the repaired recording must go to a new file, not over the one it is read from")
    count = recording.repair(args.recording, args.out)
    print(f"wrote {args.out}: the {count} messages of {args.recording}, with a summary and index")
    return 0


def render(ctx: Context, args: argparse.Namespace) -> int:
    session = SessionRef.load(args.session)
    if args.position is not None:
        if not args.data and not args.bag:
            raise ClientError("--position needs --data or --bag")
        data, format, options = dataset_source(args)
        frame = open_frames(data, format, scale=args.scale, **options).load(args.position)
        pose, camera, stamp = frame.c2w, frame.color_intrinsics, frame.timestamp
    elif args.pose and args.intrinsics and args.size:
        pose = validate_pose(np.loadtxt(args.pose).reshape(4, 4), "--pose")
        camera = parse_intrinsics(args.intrinsics, args.size)
        stamp = None
    else:
        raise ClientError("give either --data DIR (or --bag PATH) --position N, or --pose FILE --intrinsics "
                          "fx,fy,cx,cy --size WxH")
    request = pb.RenderRequest(session_id=session.session_id, c2w=matrix_to_list(pose),
                               intrinsics=intrinsics_to_proto(camera),
                               color_encoding=pb.COLOR_PNG, depth_encoding=pb.DEPTH_PNG16)
    # The pose is the client's from a frame's time (a dataset frame's own, unless named): the server moves it
    # as refinement moved the keyframe nearest that frame (RenderRequest.at).
    stamp = args.timestamp if args.timestamp is not None else stamp
    if args.sequence is not None:
        request.sequence = args.sequence
    elif stamp is not None:
        request.timestamp = stamp
    response = ctx.stub.Render(request, metadata=session.metadata())
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "color.png").write_bytes(response.color.data)
    (out / "depth.png").write_bytes(response.depth.data)
    depth = decode_depth(response.depth.data, pb.DEPTH_PNG16, response.depth.depth_scale, camera.width, camera.height)
    color = decode_color(response.color.data, pb.COLOR_PNG, camera.width, camera.height)
    far = max(float(depth.max()), 1e-3)
    preview = cv2.applyColorMap((np.clip(depth / far, 0, 1) * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    side = np.concatenate([cv2.cvtColor((color * 255).round().astype(np.uint8), cv2.COLOR_RGB2BGR), preview], 1)
    cv2.imwrite(str(out / "preview.png"), side)
    print(f"wrote {out / 'color.png'}, {out / 'depth.png'} (16-bit, millimetres) and {out / 'preview.png'} "
          f"({camera.width}x{camera.height}, {response.render_seconds * 1000:.0f} ms on the server)")
    return 0


def snapshot(ctx: Context, args: argparse.Namespace) -> int:
    session = SessionRef.load(args.session)
    data = snapshot_bytes(ctx.stub, session)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(data)
    print(f"wrote {out} ({len(data)} bytes)")
    return 0


def restore(ctx: Context, args: argparse.Namespace) -> int:
    announce(ctx.stub.RestoreSession(restore_chunks(Path(args.snapshot).read_bytes(), args.label)), args, ctx.server)
    return 0


def stats(ctx: Context, args: argparse.Namespace) -> int:
    session = SessionRef.load(args.session)
    response = ctx.stub.GetStats(pb.GetStatsRequest(session_id=session.session_id), metadata=session.metadata())
    data = {field.name: getattr(response, field.name) for field in response.DESCRIPTOR.fields}
    data["anchors_per_level"] = list(response.anchors_per_level)
    data["timings"] = dict(response.timings)
    poses = data.pop("poses")
    if response.HasField("poses"):  # a session that refines poses
        data["poses"] = {field.name: getattr(poses, field.name) for field in poses.DESCRIPTOR.fields}
    data["engine"] = json.loads(data.pop("engine_json") or "{}")
    data["config"] = json.loads(data.pop("config_json") or "{}")
    print(json.dumps(data, indent=2))
    return 0


def evaluate_command(ctx: Context, args: argparse.Namespace) -> int:
    session = SessionRef.load(args.session)
    results = evaluate(ctx.stub, session, open_frame_set(args), Path(args.out) if args.out else None,
                       progress=not args.quiet)
    print(json.dumps(results, indent=2))
    return 0


def list_sessions(ctx: Context, args: argparse.Namespace) -> int:
    response = ctx.stub.ListSessions(pb.ListSessionsRequest())
    if not response.sessions:
        print("no sessions")
    for info in response.sessions:
        print(f"{info.session_id}  preset={info.preset or 'restored'} frames={info.frames} "
              f"last_sequence={info.last_sequence} last_index={info.last_index} anchors={info.anchors} "
              f"queue={info.queue_depth} streaming={info.streaming} device={info.device} label={info.label!r}")
    return 0


def close(ctx: Context, args: argparse.Namespace) -> int:
    session = SessionRef.load(args.session)
    response = ctx.stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id),
                                     metadata=session.metadata())
    print(f"closed session {session.session_id} after {response.stats.frames} frames; recording {response.recording}"
          + (f", snapshot {response.snapshot}" if response.snapshot else "") + " in the server's record dir")
    return 0


def view(args: argparse.Namespace) -> int:
    """Serve the web view of a snapshot or a recording's map on 127.0.0.1 until interrupted."""
    path = Path(args.map)

    def ready(url: str) -> None:
        print(f"web view of {path.name} on {url}", flush=True)
        if args.open:
            webbrowser.open(url)

    return viewing.view(path, args.port, args.device, ready, args.quiet)
