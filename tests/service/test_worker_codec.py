"""What crosses between the server and its worker processes: built back as it was, and nothing else built."""

from __future__ import annotations

import json
from pathlib import Path

import grpc
import numpy as np
import pytest
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from ogapi.v1 import mapping_pb2 as pb
from ogserver.access.tokens import TokenHash
from ogserver.api.validation import RenderSpec
from ogserver.errors import ServiceError
from ogserver.live.map_look import Splats
from ogserver.live.views import MappedFrame, Pending, Shown
from ogserver.recording.disk import StorageError
from ogserver.sessions.counters import SessionCounters
from ogserver.sessions.hosting import Closed
from ogserver.workers import codec

from ogmapping.frames.camera import Intrinsics
from ogmapping.persist.export import ColoredPoints
from ogmapping.queries import Rendered
from ogmapping.stats import MapStats


def test_values_come_back_as_they_were() -> None:
    rendered = Rendered(np.random.rand(4, 5, 3).astype(np.float32), np.zeros((4, 5), np.float32),
                        np.ones((4, 5), np.float32))
    stats = MapStats(3, 1, 9, 40, (30, 10), 50, (7, 2), "cpu", "torch", {"step": 0.5}, None, {"a": {"b": [1, 2]}})
    value = ["reply", 7, True, (pb.Frame(index=3, c2w=[1.0] * 16), rendered, stats,
                                SessionCounters(1, 0, 1, 0, 0, 40, 2.5, 1.0), Path("r/x.mcap"), b"bytes", None,
                                Closed(pb.Stats(frames=2), Path("x.mcap"), None, True))]
    back = codec.loads(codec.dumps(value))
    frame, rendered_back, stats_back, counters, path, data, nothing, closed = back[3]
    assert back[:3] == ["reply", 7, True]
    assert frame == value[3][0] and isinstance(frame, pb.Frame)
    assert all(np.array_equal(getattr(rendered_back, name), getattr(rendered, name)) for name in ("color", "depth"))
    assert stats_back == stats and isinstance(stats_back.anchors_per_level, tuple)
    assert (counters, path, data, nothing, closed) == value[3][3:]


def test_what_the_live_views_read_of_a_worker_comes_back_as_it_was() -> None:
    refined = np.eye(4)
    refined[:3, 3] = (0.1, 0.2, 0.3)
    frame = MappedFrame(7, np.eye(4), Intrinsics(50.0, 50.0, 40.0, 30.0, 80, 60),
                        CompressedImage(data=b"jpeg", format="jpeg", frame_id="camera"), True, refined)
    points = ColoredPoints(np.random.rand(5, 3).astype(np.float32), np.full((5, 4), 9, np.uint8))
    value = (Pending(frame, [(7, frame.c2w)], frame, [(7, refined)]), Shown(frame, b"render", 3), Splats(b"ply", 2),
             points, TokenHash("ab" * 16, "cd" * 32))
    pending, shown, splats, points_back, token = codec.loads(codec.dumps(value))
    for back in (pending.latest, pending.keyframe, shown.frame):
        assert (back.sensor_ns, back.intrinsics, back.color, back.keyframe) == \
            (frame.sensor_ns, frame.intrinsics, frame.color, frame.keyframe)
        assert isinstance(back.color, CompressedImage) and np.array_equal(back.pose, refined)
    assert [sensor_ns for sensor_ns, _ in pending.poses + pending.refined] == [7, 7]
    assert np.array_equal(pending.refined[0][1], refined)
    assert (shown.render, shown.keyframes, splats, token) == (b"render", 3, value[2], value[4])
    assert np.array_equal(points_back.positions, points.positions) and np.array_equal(points_back.rgba, points.rgba)


def test_a_render_request_naming_its_frame_comes_back_as_it_was() -> None:
    camera = Intrinsics(50.0, 50.0, 40.0, 30.0, 80, 60)
    for sequence, timestamp in ((7, None), (None, 12.25), (None, None)):
        spec = RenderSpec(np.eye(4), camera, True, False, pb.COLOR_PNG, pb.DEPTH_PNG16, 90, sequence, timestamp)
        back = codec.loads(codec.dumps(spec))
        assert (back.sequence, back.timestamp, back.intrinsics) == (sequence, timestamp, camera)
        assert np.array_equal(back.c2w, spec.c2w)


def test_refusals_keep_their_kind_code_and_message() -> None:
    for error in (ServiceError(grpc.StatusCode.NOT_FOUND, "session_id: no session x"),
                  StorageError(grpc.StatusCode.RESOURCE_EXHAUSTED, "disk full")):
        back = codec.loads(codec.dumps(error))
        assert type(back) is type(error) and (back.code, back.message) == (error.code, error.message)
    failure = codec.loads(codec.dumps(ValueError("boom")))
    assert isinstance(failure, codec.RemoteFailure) and str(failure) == "boom"


def test_only_the_named_types_are_built() -> None:
    with pytest.raises(TypeError, match="cannot carry a object"):
        codec.dumps(object())
    header = json.dumps({"c": "Popen", "f": {"args": "true"}}).encode()
    forged = codec.HEADER.pack(len(header), 0) + header
    with pytest.raises(KeyError):
        codec.loads(forged)
