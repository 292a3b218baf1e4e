"""What crosses between the server and its worker processes: built back as it was, and nothing else built."""

from __future__ import annotations

import json
from pathlib import Path

import grpc
import numpy as np
import pytest
from ogapi.v1 import mapping_pb2 as pb
from ogserver.errors import ServiceError
from ogserver.recording.disk import StorageError
from ogserver.sessions.counters import SessionCounters
from ogserver.sessions.hosting import Closed
from ogserver.workers import codec

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
