"""End to end against one real ogserver (a subprocess here, the container with $OGMAP_SERVER).

Session A maps the tiny synthetic scene once; the other tests render it, snapshot and restore it,
replay its recording next to a second stream, score it, and throw bad inputs at a spare session.
A stays open until the last test, which closes it and reads its recording.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import grpc
import numpy as np
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from mcap.reader import make_reader
from ogapi import SERVICE_NAME, recording
from ogapi.convert import matrix_to_list
from ogapi.images import decode_color, decode_depth
from ogapi.v1 import mapping_pb2 as pb
from ogclient import replay
from ogclient.__main__ import main as ogclient_main
from ogclient.connection import SessionRef
from ogclient.evaluation import evaluate, render, snapshot_bytes
from ogclient.messages import frame_to_proto, intrinsics_to_proto
from ogclient.streaming import StreamResult, stream_frames
from ogserver import healthcheck

from ogmapping.mapper import Mapper
from ogmapping.quality.evaluation import FrameSet
from ogmapping.quality.metrics import psnr

from .bad_frames import CASES, broken
from .conftest import ServerHandle
from .proto_names import assert_spelled_as_the_proto
from .scene import FROZEN, LIMITS, TINY, create_request, messages, scene, write_ros_bag

OK = grpc.StatusCode


@dataclass
class Mapped:
    session: SessionRef
    credentials: pb.SessionCredentials
    result: StreamResult
    frames: FrameSet


def open_session(server: ServerHandle, overrides: dict[str, str], label: str) -> SessionRef:
    return SessionRef.from_credentials(server.stub.CreateSession(create_request(overrides, label)))


def stats(server: ServerHandle, session: SessionRef) -> pb.Stats:
    return server.stub.GetStats(pb.GetStatsRequest(session_id=session.session_id), metadata=session.metadata())


def close(server: ServerHandle, session: SessionRef) -> pb.CloseSessionResponse:
    request = pb.CloseSessionRequest(session_id=session.session_id)
    return server.stub.CloseSession(request, metadata=session.metadata())


@pytest.fixture(scope="module")
def mapped(server: ServerHandle) -> Mapped:
    frames = scene()
    credentials = server.stub.CreateSession(create_request(TINY, "main"))
    session = SessionRef.from_credentials(credentials)
    result = stream_frames(server.stub, session, messages(frames), progress=False)
    return Mapped(session, credentials, result, frames)


@pytest.fixture(scope="module")
def spare(server: ServerHandle) -> SessionRef:
    """A session without optimisation, for plumbing tests that map frames."""
    return open_session(server, FROZEN, "spare")


@pytest.fixture(scope="module")
def good_frame() -> pb.Frame:
    return frame_to_proto(scene("0:1").load(0))


def test_health(server: ServerHandle) -> None:
    health = health_pb2_grpc.HealthStub(server.channel)
    for service in ("", SERVICE_NAME):
        assert health.Check(health_pb2.HealthCheckRequest(service=service)).status == \
            health_pb2.HealthCheckResponse.SERVING


def test_stream_acknowledges_every_frame(mapped: Mapped) -> None:
    acks = mapped.result.acks
    assert [ack.index for ack in acks] == mapped.frames.selection.streamed
    assert all(ack.accepted for ack in acks)
    assert [ack.sequence for ack in acks] == list(range(1, len(acks) + 1))
    assert acks[0].keyframe and acks[0].iterations == int(TINY["keyframes.first_iterations"])
    assert all(ack.anchors > 0 and ack.latency_seconds >= ack.process_seconds > 0 for ack in acks)


def test_stats(server: ServerHandle, mapped: Mapped) -> None:
    current = stats(server, mapped.session)
    last = mapped.result.acks[-1]
    assert current.frames == current.frames_received == len(mapped.result.acks)
    assert current.frames_rejected == 0 and current.queue_depth == 0
    assert current.anchors == last.anchors and current.gaussians == last.gaussians
    assert current.keyframes == sum(ack.keyframe for ack in mapped.result.acks)
    assert current.processing_fps > 0 and current.preset == "sparse-fast"
    assert sum(current.anchors_per_level) == current.anchors
    assert json.loads(current.config_json)["keyframes"]["iterations"] == 2
    assert json.loads(current.engine_json)["frames"] == current.frames
    listed = {info.session_id: info for info in server.stub.ListSessions(pb.ListSessionsRequest()).sessions}
    assert listed[mapped.session.session_id].label == "main"


def test_render_matches_the_engine(server: ServerHandle, mapped: Mapped) -> None:
    local = Mapper.restore(snapshot_bytes(server.stub, mapped.session), "cpu")
    selection = mapped.frames.selection
    for position in (selection.streamed[0], selection.heldout[0]):
        frame = mapped.frames.load(position)
        remote = render(server.stub, mapped.session, frame.c2w, frame.color_intrinsics)
        mine = local.render(frame.c2w, frame.color_intrinsics)
        assert remote.color.shape == (60, 80, 3) and remote.color.std() > 0.01
        assert psnr(remote.color, mine.color) > 40.0
        assert np.abs(remote.depth - mine.depth).mean() < 0.005


def test_png_renders_equal_raw_ones(server: ServerHandle, mapped: Mapped) -> None:
    frame = mapped.frames.load(0)
    raw = render(server.stub, mapped.session, frame.c2w, frame.color_intrinsics)
    request = pb.RenderRequest(session_id=mapped.session.session_id, c2w=matrix_to_list(frame.c2w),
                               intrinsics=intrinsics_to_proto(frame.color_intrinsics))
    response = server.stub.Render(request, metadata=mapped.session.metadata())
    assert response.depth.depth_scale == 1000.0 and (response.width, response.height) == (80, 60)
    color = decode_color(response.color.data, response.color.encoding, 80, 60)
    depth = decode_depth(response.depth.data, response.depth.encoding, response.depth.depth_scale, 80, 60)
    assert np.abs(color - raw.color).max() <= 0.5 / 255 + 1e-6
    assert np.abs(depth - raw.depth).max() <= 0.0005 + 1e-6


def test_snapshot_restore_gives_identical_renders(server: ServerHandle, mapped: Mapped) -> None:
    data = snapshot_bytes(server.stub, mapped.session)
    local = Mapper.restore(data, "cpu")
    size = 64 << 10
    chunks = (pb.RestoreChunk(data=data[o : o + size], label="restored" if o == 0 else "")
              for o in range(0, len(data), size))
    restored = SessionRef.from_credentials(server.stub.RestoreSession(chunks))
    try:
        for position in (0, 5):
            frame = mapped.frames.load(position)
            remote = render(server.stub, restored, frame.c2w, frame.color_intrinsics)
            mine = local.render(frame.c2w, frame.color_intrinsics)
            np.testing.assert_allclose(remote.color, mine.color, atol=1e-6)
            np.testing.assert_allclose(remote.depth, mine.depth, atol=1e-6)
        assert stats(server, restored).anchors == stats(server, mapped.session).anchors
        more = stream_frames(server.stub, restored, messages(scene("10:12")), progress=False)
        assert all(ack.accepted for ack in more.acks) and len(more.acks) == 2
        after = stats(server, restored)
        assert after.frames == 2 and json.loads(after.engine_json)["frames"] == len(mapped.result.acks) + 2
    finally:
        close(server, restored)


def test_replay_beside_a_second_stream(server: ServerHandle, mapped: Mapped) -> None:
    assert mapped.credentials.recording == f"{mapped.session.session_id}.mcap"  # a file name, never a server path
    path = server.recorded(mapped.credentials.recording)
    if path is None:
        pytest.skip("the server's record dir is not visible here")
    recorded = recording.load(path)  # session A is still open: the file has no summary yet
    assert len(recorded.frames) == len(mapped.result.acks)
    other = scene("20:28")
    results: dict[str, tuple[SessionRef, StreamResult]] = {}

    def replay_into_new_session() -> None:
        session = SessionRef.from_credentials(server.stub.CreateSession(replay.session_request(recorded.config)))
        results["replay"] = (session, stream_frames(server.stub, session, replay.frames(recorded), progress=False))

    def stream_other_scene() -> None:
        session = open_session(server, FROZEN, "other")
        results["other"] = (session, stream_frames(server.stub, session, messages(other), progress=False))

    threads = [threading.Thread(target=replay_into_new_session), threading.Thread(target=stream_other_scene)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(timeout=300)
    replayed, replay_result = results["replay"]
    second, second_result = results["other"]
    try:
        assert [ack.index for ack in replay_result.acks] == mapped.frames.selection.streamed
        assert [ack.index for ack in second_result.acks] == other.selection.streamed
        assert replay_result.acks[-1].anchors == mapped.result.acks[-1].anchors
        assert stats(server, replayed).frames == len(mapped.result.acks)
        assert stats(server, second).frames == len(other.selection.streamed)
        original = evaluate(server.stub, mapped.session, mapped.frames, progress=False)
        again = evaluate(server.stub, replayed, mapped.frames, progress=False)
        for split in ("streamed", "heldout"):
            assert again[split]["psnr"] == pytest.approx(original[split]["psnr"], abs=1e-6)
    finally:
        close(server, replayed)
        close(server, second)


def test_eval_scores_streamed_and_heldout(server: ServerHandle, mapped: Mapped, tmp_path: Path) -> None:
    results = evaluate(server.stub, mapped.session, mapped.frames, out=tmp_path, progress=False)
    assert results["streamed"]["frames"] == 9 and results["heldout"]["frames"] == 1
    for split in ("streamed", "heldout"):
        assert 8.0 < results[split]["psnr"] < 60.0 and 0.0 < results[split]["ssim"] <= 1.0
        assert np.isfinite(results[split]["depth_l1_cm"])
    assert results["snapshot_bytes"] > 0 and results["resolution"] == [80, 60]
    assert results["client_machine"]["logical_cpus"] >= 1 and "torch" not in results["client_machine"]
    assert json.loads((tmp_path / "results.json").read_text())["anchors"] == results["anchors"]
    assert (tmp_path / "heldout_000005.png").exists()


def test_cli_against_the_server(server: ServerHandle, mapped: Mapped, tmp_path: Path,
                                capsys: pytest.CaptureFixture) -> None:
    session_file = tmp_path / "session.json"
    mapped.session.save(session_file, server.address)
    base = ["--server", server.address]
    assert ogclient_main([*base, "stats", "--session", str(session_file)]) == 0
    assert json.loads(capsys.readouterr().out)["anchors"] == mapped.result.acks[-1].anchors
    out = tmp_path / "render"
    assert ogclient_main([*base, "render", "--session", str(session_file), "--data", "synthetic", "--format",
                          "synthetic", "--scale", "0.25", "--position", "5", "--out", str(out)]) == 0
    assert {p.name for p in out.iterdir()} == {"color.png", "depth.png", "preview.png"}
    # Naming the frame a pose is from (here a session without refinement: the same render).
    at_sequence = tmp_path / "at_sequence"
    assert ogclient_main([*base, "render", "--session", str(session_file), "--data", "synthetic", "--format",
                          "synthetic", "--scale", "0.25", "--position", "5", "--sequence", "3",
                          "--out", str(at_sequence)]) == 0
    assert (at_sequence / "color.png").read_bytes() == (out / "color.png").read_bytes()
    assert ogclient_main([*base, "snapshot", "--session", str(session_file), "--out", str(tmp_path / "m.st")]) == 0
    assert (tmp_path / "m.st").stat().st_size > 0
    assert ogclient_main([*base, "list"]) == 0 and mapped.session.session_id in capsys.readouterr().out


def test_stream_a_ros_bag(server: ServerHandle, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """``ogclient stream --bag``: the reader's choices reported first, then the frames mapped like a dataset's."""
    pytest.importorskip("rosbags")  # the robots extra (make venv installs it; the container image does not)
    bag = tmp_path / "robot"
    write_ros_bag(bag, 6)
    overrides = [flag for key, value in FROZEN.items() for flag in ("--set", f"{key}={value}")]
    session_file = tmp_path / "session.json"
    code = ogclient_main(["--server", server.address, "stream", "--bag", str(bag), "--preset", "sparse-fast",
                          *overrides, "--pair-tolerance", "0.01", "--session-out", str(session_file), "--quiet"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert f"bag:{bag}: poses: /odom (nav_msgs/msg/Odometry), camera_color_optical_frame in odom" in out
    assert "6 frames: 0 colour images without depth within 0.01 s" in out
    session = SessionRef.load(session_file)
    stats = server.stub.GetStats(pb.GetStatsRequest(session_id=session.session_id), metadata=session.metadata())
    assert stats.frames == 5 and stats.frames_rejected == 0  # position 5 is held out, as for any dataset
    server.stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id), metadata=session.metadata())


def test_bad_frames_get_error_acks_and_change_nothing(server: ServerHandle, spare: SessionRef,
                                                      good_frame: pb.Frame) -> None:
    before = stats(server, spare)
    bad = []
    for number, (change, _, _) in enumerate(CASES.values()):
        message = broken(good_frame, change)
        message.index = 1000 + number
        bad.append(message)
    acks = list(server.stub.StreamFrames(iter([*bad, good_frame]), metadata=spare.stream_metadata()))
    assert len(acks) == len(CASES) + 1
    for ack, (name, (_, code, field)) in zip(acks, CASES.items(), strict=False):
        assert not ack.accepted, name
        assert (ack.error.code, ack.error.code_name) == (code.value[0], code.name), name
        assert field in ack.error.message, name
    assert acks[-1].accepted and acks[-1].index == 0 and acks[-1].sequence == before.frames_received + 1
    after = stats(server, spare)
    assert after.frames_rejected == before.frames_rejected + len(CASES)
    assert after.frames == before.frames + 1


def test_oversized_message_ends_only_that_stream(server: ServerHandle, spare: SessionRef,
                                                 good_frame: pb.Frame) -> None:
    huge = broken(good_frame, lambda m: setattr(m.color, "data", b"\x00" * (LIMITS["max_message_bytes"] + 1)))
    with pytest.raises(grpc.RpcError) as refusal:
        list(server.stub.StreamFrames(iter([huge]), metadata=spare.stream_metadata()))
    assert refusal.value.code() == OK.RESOURCE_EXHAUSTED
    deadline = time.monotonic() + 10
    while any(info.streaming for info in server.stub.ListSessions(pb.ListSessionsRequest()).sessions
              if info.session_id == spare.session_id) and time.monotonic() < deadline:
        time.sleep(0.05)
    acks = list(server.stub.StreamFrames(iter([good_frame]), metadata=spare.stream_metadata()))
    assert acks[0].accepted


def test_second_stream_on_a_session_is_refused(server: ServerHandle, spare: SessionRef,
                                               good_frame: pb.Frame) -> None:
    gate = threading.Event()

    def held():
        gate.wait(30)
        yield from ()

    first = server.stub.StreamFrames(held(), metadata=spare.stream_metadata())
    try:
        deadline = time.monotonic() + 10
        while not any(info.streaming for info in server.stub.ListSessions(pb.ListSessionsRequest()).sessions
                      if info.session_id == spare.session_id):
            assert time.monotonic() < deadline
            time.sleep(0.05)
        with pytest.raises(grpc.RpcError) as refusal:
            list(server.stub.StreamFrames(iter([good_frame]), metadata=spare.stream_metadata()))
        assert refusal.value.code() == OK.FAILED_PRECONDITION
    finally:
        gate.set()
    assert list(first) == []


def unknown(spare: SessionRef) -> SessionRef:
    return SessionRef("0" * 32, spare.token)


def render_request(session: SessionRef, c2w=None, fx: float = 70.0, width: int = 80) -> pb.RenderRequest:
    return pb.RenderRequest(
        session_id=session.session_id, c2w=np.eye(4).reshape(-1).tolist() if c2w is None else c2w,
        intrinsics=pb.CameraIntrinsics(fx=fx, fy=70, cx=40, cy=30, width=width, height=60),
    )


UNARY_CASES = {
    "unknown session": ("GetStats", lambda stub, s: stub.GetStats(
        pb.GetStatsRequest(session_id="0" * 32), metadata=s.metadata()), OK.NOT_FOUND),
    "malformed session id": ("GetStats", lambda stub, s: stub.GetStats(
        pb.GetStatsRequest(session_id="../etc"), metadata=s.metadata()), OK.INVALID_ARGUMENT),
    "wrong token": ("GetStats", lambda stub, s: stub.GetStats(
        pb.GetStatsRequest(session_id=s.session_id), metadata=SessionRef(s.session_id, "nope").metadata()),
        OK.UNAUTHENTICATED),
    "missing token": ("GetStats", lambda stub, s: stub.GetStats(
        pb.GetStatsRequest(session_id=s.session_id)), OK.UNAUTHENTICATED),
    "snapshot of unknown session": ("GetSnapshot", lambda stub, s: list(stub.GetSnapshot(
        pb.GetSnapshotRequest(session_id=unknown(s).session_id), metadata=s.metadata())), OK.NOT_FOUND),
    "close with wrong token": ("CloseSession", lambda stub, s: stub.CloseSession(
        pb.CloseSessionRequest(session_id=s.session_id), metadata=(("x-session-token", "x"),)), OK.UNAUTHENTICATED),
    "stream without session id": ("StreamFrames", lambda stub, s: list(stub.StreamFrames(
        iter([]), metadata=s.metadata())), OK.INVALID_ARGUMENT),
    "stream to unknown session": ("StreamFrames", lambda stub, s: list(stub.StreamFrames(
        iter([]), metadata=unknown(s).stream_metadata())), OK.NOT_FOUND),
    "stream with wrong token": ("StreamFrames", lambda stub, s: list(stub.StreamFrames(
        iter([]), metadata=SessionRef(s.session_id, "nope").stream_metadata())), OK.UNAUTHENTICATED),
    "render non-orthonormal pose": ("Render", lambda stub, s: stub.Render(
        render_request(s, [2.0] * 16), metadata=s.metadata()), OK.INVALID_ARGUMENT),
    "render NaN intrinsics": ("Render", lambda stub, s: stub.Render(
        render_request(s, fx=float("nan")), metadata=s.metadata()), OK.INVALID_ARGUMENT),
    "render too large": ("Render", lambda stub, s: stub.Render(
        render_request(s, width=4000), metadata=s.metadata()), OK.RESOURCE_EXHAUSTED),
    "unknown config key": ("CreateSession", lambda stub, s: stub.CreateSession(
        create_request({"keyframes.iters": "3"})), OK.INVALID_ARGUMENT),
    "bad config value": ("CreateSession", lambda stub, s: stub.CreateSession(
        create_request({"keyframes.iterations": "many"})), OK.INVALID_ARGUMENT),
    "unknown preset": ("CreateSession", lambda stub, s: stub.CreateSession(
        pb.CreateSessionRequest(preset="fastest")), OK.INVALID_ARGUMENT),
    "corrupt snapshot": ("RestoreSession", lambda stub, s: stub.RestoreSession(
        iter([pb.RestoreChunk(data=b"\x10" * 64)])), OK.INVALID_ARGUMENT),
    "empty snapshot": ("RestoreSession", lambda stub, s: stub.RestoreSession(iter([])), OK.INVALID_ARGUMENT),
}


@pytest.mark.parametrize("case", list(UNARY_CASES))
def test_bad_calls_get_their_status_and_leave_the_session_usable(server: ServerHandle, spare: SessionRef,
                                                                 case: str) -> None:
    rpc, call, code = UNARY_CASES[case]
    before = stats(server, spare)
    with pytest.raises(grpc.RpcError) as refusal:
        call(server.stub, spare)
    assert refusal.value.code() == code, refusal.value.details()
    request = pb.DESCRIPTOR.services_by_name["Mapping"].methods_by_name[rpc].input_type
    assert_spelled_as_the_proto(refusal.value.details(), request)
    after = stats(server, spare)
    assert (after.frames, after.anchors) == (before.frames, before.anchors)


def test_too_many_sessions(server: ServerHandle, spare: SessionRef) -> None:
    created = []
    try:
        with pytest.raises(grpc.RpcError) as refusal:
            for _ in range(LIMITS["max_sessions"] + 1):
                created.append(open_session(server, FROZEN, "filler"))
        assert refusal.value.code() == OK.RESOURCE_EXHAUSTED and "sessions" in refusal.value.details()
    finally:
        for session in created:
            close(server, session)
    assert stats(server, spare).frames >= 1


def test_closing_finishes_the_recording(server: ServerHandle, mapped: Mapped, spare: SessionRef,
                                       tmp_path: Path) -> None:
    spare_stats = stats(server, spare)
    closed = {name: close(server, session) for name, session in (("main", mapped.session), ("spare", spare))}
    with pytest.raises(grpc.RpcError) as refusal:
        stats(server, mapped.session)
    assert refusal.value.code() == OK.NOT_FOUND
    assert closed["main"].recording == f"{mapped.session.session_id}.mcap"  # a file name, never a server path
    path = server.recorded(closed["main"].recording)
    if path is None:
        pytest.skip("the server's record dir is not visible here")
    frames = len(mapped.result.acks)
    with open(path, "rb") as stream:
        summary = make_reader(stream).get_summary()
    counts = {channel.topic: summary.statistics.channel_message_counts[cid]
              for cid, channel in summary.channels.items()}
    schemas = {channel.topic: summary.schemas[channel.schema_id].name for channel in summary.channels.values()}
    assert counts[recording.TOPIC_FRAMES] == counts[recording.TOPIC_ACKS] == frames
    for topic in (recording.TOPIC_COLOR, recording.TOPIC_DEPTH, recording.TOPIC_TRANSFORM,
                  recording.TOPIC_CALIBRATION):
        assert counts[topic] == frames
    assert schemas[recording.TOPIC_COLOR] == "foxglove.CompressedImage"
    assert schemas[recording.TOPIC_TRANSFORM] == "foxglove.FrameTransform"
    assert counts[recording.TOPIC_SESSION] == counts[recording.TOPIC_STATS] == 1
    assert recording.load(path).stats.anchors == closed["main"].stats.anchors
    spare_path = path.with_name(closed["spare"].recording)
    spare_recorded = recording.load(spare_path)
    assert len(spare_recorded.frames) == spare_stats.frames_received  # refused frames were never recorded
    session_file = tmp_path / "replayed.json"
    assert ogclient_main(["--server", server.address, "replay", str(spare_path), "--quiet", "--close",
                          "--session-out", str(session_file)]) == 0
    replayed_id = SessionRef.load(session_file).session_id
    replayed = recording.load(path.with_name(f"{replayed_id}.mcap"))
    assert len(replayed.frames) == spare_stats.frames_received and replayed.stats is not None


def test_replay_of_a_damaged_recording_is_one_line(server: ServerHandle, tmp_path: Path,
                                                  capsys: pytest.CaptureFixture) -> None:
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 4)
    assert ogclient_main(["--server", server.address, "replay", str(damaged), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("ogclient: ") and "not a readable recording" in err


def test_container_healthcheck_module(server: ServerHandle) -> None:
    assert healthcheck.check(server.address)
