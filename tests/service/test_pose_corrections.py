"""CorrectPoses end to end: each bad batch is INVALID_ARGUMENT naming its first bad entry and changes nothing;
a good one moves the map, is recorded, and `ogclient replay` reproduces it; `ogclient correct-poses` sends a
TUM trajectory, and `ogclient stream` one from a file or a bag's topic; the batch limit and the token are
enforced."""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import grpc
import numpy as np
import pytest
from ogapi import recording
from ogapi.v1 import mapping_pb2 as pb
from ogclient.__main__ import main as ogclient_main
from ogclient.connection import SessionRef, connect
from ogclient.evaluation import snapshot_bytes
from ogclient.streaming import stream_frames
from safetensors.torch import load as load_tensors

from ogmapping.datasets import open_dataset
from ogmapping.frames.rotation import axis_angle_matrix
from ogmapping.frames.trajectory import frame_key, write_tum
from ogmapping.quality.evaluation import open_frames

from .conftest import start_local
from .inprocess import Running, serving, settings
from .scene import TINY, create_request, messages, scene, write_ros_bag

FIRST = 6  # frames streamed before the corrections; the rest after


@pytest.fixture(scope="module")
def running(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Running]:
    configured = settings(tmp_path_factory.mktemp("corrections"))
    configured.limits.max_pose_corrections = 8
    with serving(configured) as server:
        yield server


def moved(c2w: np.ndarray, degrees: float = 2.0, shift: tuple = (0.03, 0.0, -0.02)) -> np.ndarray:
    motion = np.eye(4)
    motion[:3, :3] = axis_angle_matrix(np.array([0.0, 1.0, 0.0]), np.radians(degrees))
    motion[:3, 3] = shift
    return motion @ c2w


def entry(ack: pb.FrameAck, c2w: np.ndarray, **frame) -> pb.CorrectedPose:
    return pb.CorrectedPose(c2w=c2w.reshape(-1).tolist(), **(frame or {"sequence": ack.sequence}))


def correct(stub, session: SessionRef, *poses: pb.CorrectedPose) -> pb.CorrectPosesResponse:
    request = pb.CorrectPosesRequest(session_id=session.session_id, poses=poses)
    return stub.CorrectPoses(request, metadata=session.metadata())


@pytest.fixture(scope="module")
def mapped(running: Running):
    """A session with FIRST frames mapped: (session, their acks, their messages, the rest)."""
    frames = messages(scene())
    session = SessionRef.from_credentials(running.stub.CreateSession(create_request(TINY, "corrections")))
    acks = stream_frames(running.stub, session, frames[:FIRST], progress=False).acks
    assert all(ack.accepted for ack in acks)
    return session, acks, frames[:FIRST], frames[FIRST:]


def pose_of(message: pb.Frame) -> np.ndarray:
    return np.array(message.c2w, dtype=np.float64).reshape(4, 4)


def bad_cases(acks: list[pb.FrameAck], sent: list[pb.Frame]) -> list[tuple[list[pb.CorrectedPose], str]]:
    keyframe = next(ack for ack in acks[1:] if ack.keyframe)
    pose = pose_of(sent[keyframe.sequence - 1])
    good = entry(keyframe, moved(pose))
    nan, scaled, mirrored, last_row = pose.copy(), pose.copy(), pose.copy(), pose.copy()
    nan[0, 3] = np.nan
    scaled[:3, :3] *= 1.2
    mirrored[:3, 0] *= -1.0
    last_row[3, 0] = 0.1
    far, turned = moved(pose, 0.0, (8.0, 0.0, 0.0)), moved(pose, 45.0, (0.0, 0.0, 0.0))
    stamp = sent[0].timestamp
    return [
        ([], "poses: is empty"),
        ([good, entry(keyframe, pose, sequence=99)], r"poses\[1\].sequence: frame 99 is not a frame this session"),
        ([good, entry(keyframe, pose, timestamp=stamp + 0.5)], r"poses\[1\].timestamp: no mapped frame"),
        ([good, entry(keyframe, nan)], r"poses\[1\].c2w: .*non-finite"),
        ([good, entry(keyframe, scaled)], r"poses\[1\].c2w: .*not orthonormal"),
        ([good, entry(keyframe, mirrored)], r"poses\[1\].c2w: .*reflection"),
        ([good, entry(keyframe, last_row)], r"poses\[1\].c2w: .*last row"),
        ([good, pb.CorrectedPose(c2w=pose.reshape(-1).tolist())], r"poses\[1\]: names no frame"),
        ([entry(keyframe, far)], r"poses\[0\].c2w: moves frame \d+'s camera 8 m .* beyond the server's bounds"),
        ([entry(keyframe, turned)], r"poses\[0\].c2w: moves .* 45 degrees, beyond"),
        ([good, entry(keyframe, moved(pose, 1.0))], rf"poses\[1\]: names frame {keyframe.sequence} again"),
        ([good, entry(keyframe, pose, timestamp=sent[keyframe.sequence - 1].timestamp)], r"poses\[1\]: names frame"),
        ([good, pb.CorrectedPose(sequence=1, c2w=[1.0] * 12)], r"poses\[1\].c2w: must hold 16 numbers"),
    ]


def test_bad_batches_are_refused_and_change_nothing(running: Running, mapped) -> None:
    session, acks, sent, _ = mapped
    before = snapshot_bytes(running.stub, session)
    for poses, message in bad_cases(acks, sent):
        with pytest.raises(grpc.RpcError) as refused:
            correct(running.stub, session, *poses)
        assert refused.value.code() == grpc.StatusCode.INVALID_ARGUMENT, message
        assert re.search(message, refused.value.details()), (message, refused.value.details())
    too_many = [entry(acks[0], pose_of(sent[0]))] * 9
    with pytest.raises(grpc.RpcError) as refused:
        correct(running.stub, session, *too_many)
    assert refused.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert "limits.max_pose_corrections" in refused.value.details()
    with pytest.raises(grpc.RpcError) as refused:
        running.stub.CorrectPoses(pb.CorrectPosesRequest(session_id=session.session_id),
                                  metadata=(("x-session-token", "x" * 43),))
    assert refused.value.code() == grpc.StatusCode.UNAUTHENTICATED
    after = load_tensors(snapshot_bytes(running.stub, session))
    before = load_tensors(before)
    assert after.keys() == before.keys()
    assert all(bool((after[name] == before[name]).all()) for name in before)


def anchors(data: bytes) -> dict:
    tensors = load_tensors(data)
    return {name: tensors[f"anchors.{name}"] for name in ("positions", "keyframe", "codes")}


def test_a_correction_moves_the_map_and_replays(running: Running, mapped, tmp_path: Path) -> None:
    session, acks, sent, rest = mapped
    keyframes = [ack for ack in acks if ack.keyframe]
    target = keyframes[-1]
    owner = len(keyframes) - 1
    before = anchors(snapshot_bytes(running.stub, session))
    mine = before["keyframe"] == owner
    assert bool(mine.any())
    pose = pose_of(sent[target.sequence - 1])
    plain = next((ack for ack in acks if not ack.keyframe), None)
    batch = [entry(target, moved(pose), timestamp=sent[target.sequence - 1].timestamp)]
    if plain is not None:
        batch.append(entry(plain, pose_of(sent[plain.sequence - 1])))
    response = correct(running.stub, session, *batch)
    assert (response.keyframes, response.frames) == (1, len(batch) - 1)
    assert response.anchors_moved == int(mine.sum()) and response.after_sequence == FIRST
    after = anchors(snapshot_bytes(running.stub, session))
    motion = moved(pose) @ np.linalg.inv(pose)
    expected = before["positions"][mine].double().numpy() @ motion[:3, :3].T + motion[:3, 3]
    assert np.allclose(after["positions"][mine].double().numpy(), expected, atol=1e-5)
    assert np.array_equal(after["positions"][~mine].numpy(), before["positions"][~mine].numpy())

    # The rest of the frames, then a TUM file through `ogclient correct-poses`.
    stream_frames(running.stub, session, rest, progress=False)
    session_file = tmp_path / "session.json"
    session.save(session_file, running.address)
    tum = tmp_path / "corrected.tum"
    write_tum(tum, [sent[0].timestamp], [moved(pose_of(sent[0]), 1.0, (0.0, 0.01, 0.0))], ["corrected"])
    assert ogclient_main(["--server", running.address, "correct-poses", "--session", str(session_file),
                          str(tum)]) == 0
    live = anchors(snapshot_bytes(running.stub, session))
    closed = running.stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id),
                                       metadata=session.metadata())
    recorded = recording.load(running.record_dir / closed.recording)
    assert [batch.after_sequence for batch in recorded.corrections] == [FIRST, len(sent) + len(rest)]
    assert all(pose.HasField("sequence") for batch in recorded.corrections for pose in batch.poses)

    replayed_file = tmp_path / "replayed.json"
    assert ogclient_main(["--server", running.address, "replay", str(running.record_dir / closed.recording),
                          "--session-out", str(replayed_file), "--quiet"]) == 0
    replayed = anchors(snapshot_bytes(running.stub, SessionRef.load(replayed_file)))
    assert torch_equal(replayed["keyframe"], live["keyframe"])
    assert np.allclose(replayed["positions"].numpy(), live["positions"].numpy(), atol=1e-6)


def torch_equal(first, second) -> bool:
    return first.shape == second.shape and bool((first == second).all())


def test_a_resumed_session_keeps_its_corrections(tmp_path: Path) -> None:
    """kill -9 after a correction a checkpoint holds and one made after it: the next server's session has both
    (the second applied again from the recording), once each, and still resolves the frames before its
    checkpoint."""
    record_dir = tmp_path / "recordings"
    frames = messages(scene())
    first = start_local(record_dir, "--checkpoint-interval", "2", "--no-warm-up")
    try:
        channel, stub = connect(first.address, timeout=60.0)
        session = SessionRef.from_credentials(stub.CreateSession(create_request(TINY, "resume")))
        acks = stream_frames(stub, session, frames[:4], progress=False).acks
        keyframes = [ack for ack in acks if ack.keyframe]
        correct(stub, session, entry(keyframes[-1], moved(pose_of(frames[keyframes[-1].sequence - 1]))))
        stream_frames(stub, session, frames[4:6], progress=False)  # the checkpoint at frame 6 holds the correction
        correct(stub, session, entry(keyframes[0], moved(pose_of(frames[0]), 1.0, (0.0, 0.02, 0.0))))
        live = anchors(snapshot_bytes(stub, session))
        channel.close()
    finally:
        first.kill()
    second = start_local(record_dir, "--checkpoint-interval", "2", "--no-warm-up")
    try:
        channel, stub = connect(second.address, timeout=60.0)
        assert "resumed for" in second.log_path.read_text()
        resumed = anchors(snapshot_bytes(stub, session))
        assert torch_equal(resumed["keyframe"], live["keyframe"])
        assert np.allclose(resumed["positions"].numpy(), live["positions"].numpy(), atol=1e-6)
        again = correct(stub, session, entry(acks[1], pose_of(frames[1])))
        assert again.after_sequence == 6
        channel.close()
    finally:
        second.stop()


def test_a_stream_sends_its_corrected_trajectory_at_the_end(running: Running, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture) -> None:
    """`ogclient stream --corrected-trajectory` (as for a bag): the file's poses of the frames it mapped, matched by
    key, sent once they are mapped; lines of other frames are left out."""
    frame_set = open_frames("synthetic", "synthetic", "0:6", 1, 0.25)  # what the command streams
    streamed = [frame_set.load(position) for position in frame_set.selection.streamed]
    tum = tmp_path / "slam.tum"
    keys = [frame_key(frame) for frame in streamed] + [1000.0]
    write_tum(tum, keys, [moved(frame.c2w, 0.5, (0.01, 0.0, 0.0)) for frame in streamed] + [np.eye(4)], ["slam"])
    session_file = tmp_path / "streamed.json"
    assert ogclient_main(["--server", running.address, "stream", "--data", "synthetic", "--format", "synthetic",
                          "--frames", "0:6", "--scale", "0.25", "--preset", "sparse-fast", "--quiet",
                          *(item for key, value in TINY.items() for item in ("--set", f"{key}={value}")),
                          "--session-out", str(session_file), "--corrected-trajectory", str(tum), "--close"]) == 0
    said = re.search(rf"{len(streamed)} of its {len(keys)} poses are of frames mapped here; 1 batches applied: "
                     r"(\d+) keyframes corrected \((\d+) anchors moved\)", out := capsys.readouterr().out)
    assert said, out
    assert int(said.group(1)) >= 1 and int(said.group(2)) > 0


def test_a_stream_sends_the_corrected_path_on_a_bag_topic(running: Running, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture) -> None:
    """`ogclient stream --bag --corrected-topic`: the bag's SLAM path (its camera poses in the pose topic's frame)
    corrects the session as the same poses sent as a TUM file with --corrected-trajectory do; a topic that is no
    corrected trajectory is refused before a session is opened."""
    pytest.importorskip("rosbags")
    frames = scene("0:6")
    corrected = [moved(frames.load(i).c2w, 0.5, (0.01, 0.0, 0.0)) for i in range(6)]
    bag = tmp_path / "robot"
    write_ros_bag(bag, 6, corrected)
    tum = tmp_path / "slam.tum"
    write_tum(tum, [frame.timestamp for frame in open_dataset(str(bag), "bag", corrected_topic="/slam/path")],
              corrected, ["slam"])

    def stream(*flags: str) -> tuple[str, dict]:
        """What the stream said of its corrections, and the map they left."""
        session_file = tmp_path / "session.json"
        assert ogclient_main(["--server", running.address, "stream", "--bag", str(bag), "--preset", "sparse-fast",
                              *(item for key, value in TINY.items() for item in ("--set", f"{key}={value}")),
                              "--quiet", "--session-out", str(session_file), *flags]) == 0
        said = re.search(r": (5 of its 6 poses are of frames mapped here; .*)", out := capsys.readouterr().out)
        assert said, out
        session = SessionRef.load(session_file)
        live = anchors(snapshot_bytes(running.stub, session))
        running.stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id), metadata=session.metadata())
        return said.group(1), live

    from_topic, from_file = stream("--corrected-topic", "/slam/path"), stream("--corrected-trajectory", str(tum))
    assert from_topic[0] == from_file[0] and re.search(r"[1-9]\d* keyframes corrected", from_topic[0])
    assert torch_equal(from_topic[1]["keyframe"], from_file[1]["keyframe"])
    assert np.allclose(from_topic[1]["positions"].numpy(), from_file[1]["positions"].numpy(), atol=1e-6)

    refused = tmp_path / "refused.json"
    assert ogclient_main(["--server", running.address, "stream", "--bag", str(bag), "--session-out", str(refused),
                          "--corrected-topic", "/camera/color/camera_info"]) == 2
    assert "--corrected-topic /camera/color/camera_info is a sensor_msgs/msg/CameraInfo topic" in \
        capsys.readouterr().err
    assert not refused.exists()
