"""The recordings' map views: keyframes' render and point cloud, and the final map when a session closes."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from ogapi import recording
from ogapi.v1 import mapping_pb2 as pb
from ogclient.connection import SessionRef
from ogclient.streaming import stream_frames

from .inprocess import serving, settings
from .scene import FROZEN, create_request, messages, scene


@pytest.mark.parametrize("record_views", [True, False])
def test_a_closed_recording_ends_with_the_final_map(tmp_path, record_views: bool) -> None:
    configured = settings(tmp_path)
    configured.live.view_seconds = 3600.0  # the thread never looks: only the close writes a view
    configured.live.record_views = record_views
    frames = messages(scene())
    with serving(configured) as running:
        credentials = running.stub.CreateSession(create_request(FROZEN))
        session = SessionRef.from_credentials(credentials)
        acks = stream_frames(running.stub, session, frames, progress=False).mapped
        running.stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id), metadata=session.metadata())
    items = list(recording.read_messages(Path(configured.record_dir) / credentials.recording))
    counts = Counter(item.topic for item in items)
    if not record_views:
        assert recording.TOPIC_RENDER not in counts and recording.TOPIC_MAP not in counts
        return
    assert counts[recording.TOPIC_RENDER] == counts[recording.TOPIC_MAP] == 1
    cloud = PointCloud.FromString(next(item.data for item in items if item.topic == recording.TOPIC_MAP))
    assert cloud.frame_id == recording.WORLD_FRAME and len(cloud.data) // cloud.point_stride > 0
    # The view is of the last keyframe, after every frame was mapped: it comes after the last frame.
    last_keyframe = max(position for position, ack in enumerate(acks) if ack.keyframe)
    stamp = cloud.timestamp.ToNanoseconds()
    assert stamp == round(frames[last_keyframe].timestamp * 1e9)
    topics = [item.topic for item in items]
    assert topics.index(recording.TOPIC_MAP) > max(np.flatnonzero(np.array(topics) == recording.TOPIC_FRAMES))
