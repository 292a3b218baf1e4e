"""The live view: a Foxglove WebSocket client sees a session's render, trajectory and map, and the
recording carries the keyframes' render and map under the same schemas."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from ogapi import recording
from ogapi.v1 import mapping_pb2 as pb
from ogclient.connection import SessionRef
from ogclient.streaming import stream_frames
from ogserver.live.publisher import LIVE_TOPICS, session_prefix

from .inprocess import serving, settings
from .scene import TINY, create_request, messages, scene

pytest.importorskip("foxglove", reason="the live extra (foxglove-sdk) is not installed")
foxglove_client = pytest.importorskip("tests.service.foxglove_client", reason="websockets is not installed")

MAX_POINTS = 400


def wait_for(condition, seconds: float = 10.0) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


def test_foxglove_client_sees_render_transform_and_point_cloud(tmp_path) -> None:
    configured = settings(tmp_path)
    configured.live.foxglove_port = 0
    configured.live.view_seconds = 0.2
    configured.live.view_points = MAX_POINTS
    frames = messages(scene())
    with serving(configured) as running:
        fox = running.server.live.foxglove
        credentials = running.stub.CreateSession(create_request(TINY))
        session = SessionRef.from_credentials(credentials)
        prefix = session_prefix(session.session_id)
        topics = list(LIVE_TOPICS)
        url = f"ws://127.0.0.1:{fox.port}"

        async def watch_while_streaming():
            watcher = asyncio.create_task(foxglove_client.watch(url, prefix, topics, {prefix + t for t in topics}, 30))
            # Stream once the client has subscribed to every topic of the session.
            await asyncio.to_thread(wait_for, lambda: all(fox.wants(prefix + topic) for topic in topics))
            await asyncio.to_thread(stream_frames, running.stub, session, frames, None, False)
            return await watcher

        received = asyncio.run(watch_while_streaming())
        running.stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id), metadata=session.metadata())

    poses = {tuple(np.round(np.array(frame.c2w).reshape(4, 4)[:3, 3], 6)) for frame in frames}
    transforms = [message for _, message in received.messages[prefix + recording.TOPIC_TRANSFORM]]
    assert received.channels[prefix + recording.TOPIC_TRANSFORM].schema_name == "foxglove.FrameTransform"
    for transform in transforms:
        assert transform.parent_frame_id == f"{session.session_id}/world"
        assert transform.child_frame_id == f"{session.session_id}/camera"
        assert tuple(np.round([transform.translation.x, transform.translation.y, transform.translation.z], 6)) in poses

    width, height = frames[0].color_intrinsics.width, frames[0].color_intrinsics.height
    _, render = received.messages[prefix + recording.TOPIC_RENDER][-1]
    assert received.channels[prefix + recording.TOPIC_RENDER].schema_name == "foxglove.CompressedImage"
    assert render.format == "jpeg"
    image = cv2.imdecode(np.frombuffer(render.data, np.uint8), cv2.IMREAD_COLOR)
    assert image.shape == (height, width, 3) and image.std() > 1.0, "the render is blank"
    _, color = received.messages[prefix + recording.TOPIC_COLOR][-1]
    assert color.data in {frame.color.data for frame in frames}, "the input image is not one that was sent"

    assert received.channels[prefix + recording.TOPIC_MAP].schema_name == "foxglove.PointCloud"
    _, cloud = received.messages[prefix + recording.TOPIC_MAP][-1]
    points = decode_points(cloud)
    assert 0 < len(points) <= MAX_POINTS and np.isfinite(points["xyz"]).all()
    assert cloud.frame_id == f"{session.session_id}/world"

    # The recording: the keyframes' render and map under the same schemas, readable as before.
    path = Path(configured.record_dir) / credentials.recording
    recorded = recording.load(path)
    assert len(recorded.frames) == len(frames)
    schemas = {item.topic: item.schema for item in recording.read_messages(path)}
    assert schemas[recording.TOPIC_RENDER] == "foxglove.CompressedImage"
    assert schemas[recording.TOPIC_MAP] == "foxglove.PointCloud"
    repaired = tmp_path / "repaired.mcap"
    recording.repair(path, repaired)
    maps = list(recording.read_messages(repaired, {recording.TOPIC_MAP}))
    assert maps and all(0 < len(decode_points(type(cloud).FromString(item.data))) <= MAX_POINTS for item in maps)


def decode_points(cloud) -> np.ndarray:
    """Points by the cloud's own field table: x, y, z float32, then RGBA bytes."""
    offsets = {field.name: field.offset for field in cloud.fields}
    assert cloud.point_stride == 16 and offsets == {"x": 0, "y": 4, "z": 8, "red": 12, "green": 13, "blue": 14,
                                                    "alpha": 15}
    return np.frombuffer(cloud.data, dtype=[("xyz", "<f4", 3), ("rgba", "u1", 4)])


def test_without_the_port_no_foxglove_server_starts(tmp_path) -> None:
    with serving(settings(tmp_path)) as running:
        assert running.server.live is not None and running.server.live.foxglove is None
