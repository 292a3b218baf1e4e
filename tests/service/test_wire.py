"""Messages that do not parse, against a server in this process: INVALID_ARGUMENT, a stream that
goes on, and one throttled log line instead of a traceback per call."""

from __future__ import annotations

import logging
from collections.abc import Iterator

import grpc
import pytest
from ogapi import SERVICE_NAME
from ogapi.v1 import mapping_pb2 as pb
from ogclient.connection import SessionRef, connect
from ogclient.messages import frame_to_proto
from ogserver.app import Server, build
from ogserver.settings import Limits, Settings

from .scene import FROZEN, LIMITS, create_request, scene

GARBAGE = b"\xff\xff\xff\xff"  # a varint that never ends: no message parses it
METHODS = pb.DESCRIPTOR.services_by_name["Mapping"].methods


@pytest.fixture(scope="module")
def local(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    settings = Settings(address="127.0.0.1:0", record_dir=str(tmp_path_factory.mktemp("wire")), device="cpu",
                        warm_up=False, torch_threads=1, limits=Limits(**LIMITS))
    server = build(settings)
    try:
        yield server
    finally:
        server.stop(0, 5)


def raw_call(channel: grpc.Channel, method, requests: list[bytes], metadata=()):
    """Call ``method`` with request bytes as they are, whatever its kind."""
    path = f"/{SERVICE_NAME}/{method.name}"
    kind = ("stream" if method.client_streaming else "unary") + "_" + ("stream" if method.server_streaming else "unary")
    call = getattr(channel, kind)(path, request_serializer=None, response_deserializer=None)
    argument = iter(requests) if method.client_streaming else requests[0]
    response = call(argument, metadata=metadata, timeout=30)
    return list(response) if method.server_streaming else response


@pytest.mark.parametrize("method", [m for m in METHODS if m.name != "StreamFrames"], ids=lambda m: m.name)
def test_a_request_that_does_not_parse_is_invalid_argument(local: Server, method,
                                                           caplog: pytest.LogCaptureFixture) -> None:
    channel, _ = connect(f"127.0.0.1:{local.port}", timeout=30)
    with channel, caplog.at_level(logging.WARNING):
        with pytest.raises(grpc.RpcError) as refusal:
            for _ in range(3):
                raw_call(channel, method, [GARBAGE])
        assert refusal.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        assert refusal.value.details() == f"the message does not parse as {method.input_type.full_name} (4 bytes)"
    assert not [record for record in caplog.records if record.levelno >= logging.ERROR]


def test_a_frame_that_does_not_parse_gets_an_error_ack_and_the_stream_goes_on(
    local: Server, caplog: pytest.LogCaptureFixture
) -> None:
    channel, stub = connect(f"127.0.0.1:{local.port}", timeout=30)
    frames = scene("0:2")
    good = [frame_to_proto(frames.load(position)).SerializeToString() for position in range(2)]
    with channel, caplog.at_level(logging.WARNING):
        ref = SessionRef.from_credentials(stub.CreateSession(create_request(FROZEN, "wire")))
        method = pb.DESCRIPTOR.services_by_name["Mapping"].methods_by_name["StreamFrames"]
        replies = raw_call(channel, method, [good[0], GARBAGE, GARBAGE, good[1]], ref.stream_metadata())
        acks = sorted((pb.FrameAck.FromString(reply) for reply in replies), key=lambda ack: ack.accepted)
        assert [ack.accepted for ack in acks] == [False, False, True, True]
        assert {ack.error.code_name for ack in acks[:2]} == {"INVALID_ARGUMENT"}
        assert "does not parse as ogapi.v1.Frame" in acks[0].error.message
        stats = stub.GetStats(pb.GetStatsRequest(session_id=ref.session_id), metadata=ref.metadata())
        assert (stats.frames, stats.frames_rejected) == (2, 2)
    warnings = [record for record in caplog.records if record.name == "ogserver.api.wire"]
    assert len(warnings) <= 1  # throttled: one line per interval, however many arrive
    assert not [record for record in caplog.records if record.levelno >= logging.ERROR]
