"""Refined poses are results: the acks and Stats of a session with poses.refine report the correction,
a clamped one is counted and logged, the recording keeps the refined poses beside the client's, a replay
refines them the same, and ogclient writes either trajectory in TUM format."""

from __future__ import annotations

import json
import logging
import urllib.request
from pathlib import Path

import grpc
import numpy as np
import pytest
from ogapi import recording
from ogapi.convert import matrix_to_list
from ogapi.images import decode_color
from ogapi.v1 import mapping_pb2 as pb
from ogclient.__main__ import main as ogclient_main
from ogclient.connection import SessionRef
from ogclient.evaluation import render, snapshot_bytes
from ogclient.messages import intrinsics_to_proto

from ogmapping.frames.rotation import matrix_to_quaternion
from ogmapping.frames.trajectory import read_tum
from ogmapping.mapper import Mapper
from ogmapping.quality.metrics import psnr

from .inprocess import serving, settings
from .scene import PRESET, TINY, create_request, messages, scene

# Corrections that reach a bound of a tenth of a millimetre within a frame's few steps (every pose moves:
# held at the client's pose, none would stay at the bound).
REFINE = {**TINY, "poses.refine": "true", "poses.translation_lr": "0.01", "poses.max_translation": "0.0001",
          "poses.track_min_gain": "0"}


def matrix(numbers) -> np.ndarray:
    return np.array(list(numbers), dtype=np.float64).reshape(4, 4)


def same_pose(a: np.ndarray, b: np.ndarray) -> bool:
    """As a TUM line keeps it: the centre exactly, the rotation as a unit quaternion (either sign)."""
    qa, qb = np.array(matrix_to_quaternion(a[:3, :3])), np.array(matrix_to_quaternion(b[:3, :3]))
    return bool(np.array_equal(a[:3, 3], b[:3, 3]) and min(np.abs(qa - qb).max(), np.abs(qa + qb).max()) < 1e-12)


def test_a_refining_session_reports_records_and_replays_its_corrections(tmp_path: Path, caplog, capsys) -> None:
    configured = settings(tmp_path)
    configured.access.metrics_address = "127.0.0.1:0"
    frames = messages(scene())
    with serving(configured) as running, caplog.at_level(logging.WARNING, logger="ogserver.sessions.session"):
        credentials = running.stub.CreateSession(create_request(REFINE))
        session = SessionRef.from_credentials(credentials)
        acks = list(running.stub.StreamFrames(iter(frames), metadata=session.stream_metadata(), timeout=120))
        stats = running.stub.GetStats(pb.GetStatsRequest(session_id=session.session_id), metadata=session.metadata())
        with urllib.request.urlopen(f"http://127.0.0.1:{running.server.metrics.port}/metrics", timeout=5) as page:
            scraped = page.read().decode()
        session.save(tmp_path / "session.json", running.address)
        capsys.readouterr()
        assert ogclient_main(["--server", running.address, "stats", "--session", str(tmp_path / "session.json")]) == 0
        printed = json.loads(capsys.readouterr().out)["poses"]
        renders_at_frame_times(running.stub, session, acks)
        running.stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id), metadata=session.metadata())
        path = running.record_dir / credentials.recording

        # Every mapped frame's ack carries its correction; the first keeps the client's pose.
        assert all(ack.accepted and ack.HasField("pose_correction") for ack in acks)
        first = acks[0].pose_correction
        assert list(first.translation) == [0.0] * 3 and list(first.rotation) == [0.0] * 3 and not first.clamped
        assert np.array_equal(matrix(first.refined_c2w), matrix(frames[0].c2w))
        clamped = [ack for ack in acks if ack.pose_correction.clamped]
        assert clamped, "no correction reached the tenth-of-a-millimetre bound"
        for ack, frame in zip(acks, frames, strict=True):
            correction = ack.pose_correction
            assert np.linalg.norm(correction.translation) <= 1e-4 * (1 + 1e-5)
            refined, client = matrix(correction.refined_c2w), matrix(frame.c2w)
            assert np.allclose(refined[:3, 3], client[:3, 3] + np.array(correction.translation), atol=1e-6)
        assert f"ogserver_clamped_pose_corrections_total {float(len(clamped))}" in scraped
        assert any("pose correction reached the bound" in record.getMessage() for record in caplog.records)
        keyframes = sum(ack.keyframe for ack in acks)
        assert stats.HasField("poses") and stats.poses.refined_keyframes == keyframes - 1
        assert 0 < stats.poses.max_correction_m <= 1e-4 * (1 + 1e-5) and stats.poses.clamped_keyframes >= 1
        assert printed == {"refined_keyframes": keyframes - 1, "mean_correction_m": stats.poses.mean_correction_m,
                           "max_correction_m": stats.poses.max_correction_m,
                           "mean_correction_deg": stats.poses.mean_correction_deg,
                           "max_correction_deg": stats.poses.max_correction_deg,
                           "clamped_keyframes": stats.poses.clamped_keyframes}

        # The recording keeps both poses: the frames as sent, each ack's refined pose and a Foxglove transform.
        recorded = recording.load(path)
        assert [ack.pose_correction for ack in recorded.acks] == [ack.pose_correction for ack in acks]
        assert recorded.stats.poses == stats.poses
        transforms = list(recording.read_messages(path, {recording.TOPIC_REFINED_TRANSFORM}))
        assert len(transforms) == len(acks) and transforms[0].schema == "foxglove.FrameTransform"

        refined_file, client_file = tmp_path / "refined.tum", tmp_path / "client.tum"
        assert ogclient_main(["trajectory", str(path), "--out", str(refined_file)]) == 0
        assert ogclient_main(["trajectory", str(path), "--out", str(client_file), "--client"]) == 0
        refined, sent = read_tum(refined_file), read_tum(client_file)
        assert list(refined.keys) == list(sent.keys) == [frame.timestamp for frame in frames]
        assert all(same_pose(pose, matrix(ack.pose_correction.refined_c2w)) for pose, ack in
                   zip(refined.poses, acks, strict=True))
        assert all(same_pose(pose, matrix(frame.c2w)) for pose, frame in zip(sent.poses, frames, strict=True))

        # A replay feeds the client's poses and refines them as the recorded session did.
        replayed_file = tmp_path / "replayed.tum"
        code = ogclient_main(["--server", running.address, "replay", str(path), "--quiet", "--close",
                              "--session-out", str(tmp_path / "replay.json"), "--trajectory", str(replayed_file)])
        assert code == 0
        assert replayed_file.read_text().splitlines()[1:] == refined_file.read_text().splitlines()[1:]


def renders_at_frame_times(stub, session: SessionRef, acks: list[pb.FrameAck]) -> None:
    """A render naming a frame (by sequence or timestamp) is at the pose moved as the keyframe nearest it was
    refined: as a local map made from the session's snapshot renders it, and not as the unmoved pose does."""
    local = Mapper.restore(snapshot_bytes(stub, session))
    frames = scene()
    frame = frames.load(frames.selection.streamed[-1])
    by_time = render(stub, session, frame.c2w, frame.color_intrinsics, frame)
    unmoved = render(stub, session, frame.c2w, frame.color_intrinsics)
    request = pb.RenderRequest(session_id=session.session_id, c2w=matrix_to_list(frame.c2w), sequence=acks[-1].sequence,
                               intrinsics=intrinsics_to_proto(frame.color_intrinsics),
                               color_encoding=pb.COLOR_RAW_F32, depth_encoding=pb.DEPTH_RAW_F32)
    response = stub.Render(request, metadata=session.metadata())
    camera = frame.color_intrinsics
    by_sequence = decode_color(response.color.data, pb.COLOR_RAW_F32, camera.width, camera.height)
    mine = local.render(frame.c2w, camera, local.nearest_keyframe(frame.index)).color
    assert np.array_equal(by_sequence, by_time.color)
    assert psnr(by_time.color, mine) > 40.0 and not np.array_equal(by_time.color, unmoved.color)


def test_without_refinement_acks_and_stats_carry_no_poses(tmp_path: Path, capsys) -> None:
    frames = messages(scene("0:3"))
    with serving(settings(tmp_path)) as running:
        credentials = running.stub.CreateSession(create_request(TINY))
        session = SessionRef.from_credentials(credentials)
        acks = list(running.stub.StreamFrames(iter(frames), metadata=session.stream_metadata(), timeout=60))
        stats = running.stub.GetStats(pb.GetStatsRequest(session_id=session.session_id), metadata=session.metadata())
        session.save(tmp_path / "session.json", running.address)
        assert ogclient_main(["--server", running.address, "stats", "--session", str(tmp_path / "session.json")]) == 0
        assert "poses" not in json.loads(capsys.readouterr().out)
        running.stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id), metadata=session.metadata())
        path = running.record_dir / credentials.recording
    assert acks and not any(ack.HasField("pose_correction") for ack in acks)
    assert not stats.HasField("poses") and "poses" not in stats.engine_json
    assert not list(recording.read_messages(path, {recording.TOPIC_REFINED_TRANSFORM}))
    assert ogclient_main(["trajectory", str(path), "--out", str(tmp_path / "refined.tum")]) == 2
    assert "did not refine poses (poses.refine); --client writes the client's" in capsys.readouterr().err
    assert not (tmp_path / "refined.tum").exists()


@pytest.mark.parametrize(("key", "value"), [("poses.refine", "maybe"), ("poses.max_translation", "-1")])
def test_a_bad_poses_value_is_invalid_argument(tmp_path: Path, key: str, value: str) -> None:
    with serving(settings(tmp_path)) as running, pytest.raises(grpc.RpcError) as caught:
        running.stub.CreateSession(pb.CreateSessionRequest(preset=PRESET, overrides={key: value}))
    assert caught.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert key in caught.value.details() and "\n" not in caught.value.details()


def test_ogclient_stream_writes_the_refined_trajectory(tmp_path: Path, capsys) -> None:
    dataset = ["--data", "synthetic", "--format", "synthetic", "--frames", "0:4", "--scale", "0.25", "--quiet",
               "--preset", PRESET]
    with serving(settings(tmp_path)) as running:
        base = ["--server", running.address, "stream", *dataset, "--close", "--session-out", str(tmp_path / "s.json")]
        streamed = tmp_path / "streamed.tum"
        refine = [item for key, value in REFINE.items() for item in ("--set", f"{key}={value}")]
        assert ogclient_main([*base, *refine, "--trajectory", str(streamed)]) == 0
        path = running.record_dir / f"{SessionRef.load(tmp_path / 's.json').session_id}.mcap"
        assert ogclient_main(["trajectory", str(path), "--out", str(tmp_path / "recorded.tum")]) == 0
        lines = streamed.read_text().splitlines()
        assert len(lines) == 2 + 4 and lines[2:] == (tmp_path / "recorded.tum").read_text().splitlines()[2:]

        plain = tmp_path / "plain.tum"
        capsys.readouterr()
        assert ogclient_main([*base, "--set", "keyframes.iterations=2", "--trajectory", str(plain)]) == 2
        assert "does not refine poses: poses.refine" in capsys.readouterr().err and not plain.exists()
