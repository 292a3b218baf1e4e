"""Calls that send their headers and never their request message, from a client with no API key: they
must not take what health checks, keyed calls and running frame streams need, and they are ended."""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import grpc
import pytest
from grpc_health.v1 import health_pb2
from ogapi import SERVICE_NAME
from ogapi.v1 import mapping_pb2 as pb
from ogclient.connection import SessionRef
from ogserver import apikeys

from .inprocess import Running, serving, settings
from .scene import FROZEN, create_request, messages, scene
from .test_access import KEYS, as_caller, health_check

# Unary methods of every kind the server has: mapping calls that need a key, a token, and none (health).
HEADER_ONLY_METHODS = (f"/{SERVICE_NAME}/ListSessions", f"/{SERVICE_NAME}/GetStats",
                       f"/{SERVICE_NAME}/CreateSession", "/grpc.health.v1.Health/Check")


@contextmanager
def header_only_calls(address: str, count: int) -> Iterator[list[grpc.Future]]:
    """``count`` unary calls on one connection that send their headers and then nothing until the block ends."""
    release = threading.Event()

    def nothing() -> Iterator[bytes]:
        release.wait()
        yield from ()

    channel = grpc.insecure_channel(address, options=[("grpc.use_local_subchannel_pool", 1)])
    calls = [channel.stream_unary(HEADER_ONLY_METHODS[index % len(HEADER_ONLY_METHODS)]).future(nothing())
             for index in range(count)]
    try:
        time.sleep(1.0)  # time to reach the server
        yield calls
    finally:
        release.set()
        for call in calls:
            call.cancel()
        channel.close()


@pytest.fixture
def keyed_stream(tmp_path: Path) -> Iterator[tuple[Running, object, object, queue.Queue]]:
    """A keyed server where alice has a session and a frame stream open (one frame acknowledged)."""
    configured = settings(tmp_path)
    configured.access.api_keys = {name: apikeys.digest(key) for name, key in KEYS.items()}
    configured.access.request_seconds = 3.0
    with serving(configured) as running:
        channel, alice = as_caller(running, "alice")
        session = SessionRef.from_credentials(alice.CreateSession(create_request(FROZEN)))
        feed: queue.Queue[pb.Frame | None] = queue.Queue()
        acks = alice.StreamFrames(iter(feed.get, None), metadata=session.stream_metadata(), timeout=40)
        try:
            yield running, alice, acks, feed
        finally:
            feed.put(None)
            acks.cancel()
            channel.close()


@pytest.mark.parametrize("count", [40, 400])
def test_header_only_calls_leave_health_keyed_calls_and_streams_answering(keyed_stream, count: int) -> None:
    running, alice, acks, feed = keyed_stream
    frames = messages(scene("0:3"))
    feed.put(frames[0])
    assert next(acks).accepted
    with header_only_calls(running.address, count):
        start = time.monotonic()
        assert health_check(running.address, timeout=2.0) == health_pb2.HealthCheckResponse.SERVING
        assert len(alice.ListSessions(pb.ListSessionsRequest(), timeout=2.0).sessions) == 1
        feed.put(frames[1])
        assert next(acks).accepted
        assert time.monotonic() - start < 20.0


def test_a_call_whose_request_never_comes_is_ended_and_logged(keyed_stream,
                                                               caplog: pytest.LogCaptureFixture) -> None:
    running = keyed_stream[0]
    with caplog.at_level(logging.WARNING), header_only_calls(running.address, 4) as calls:
        for call in calls:
            error = call.exception(timeout=10)
            assert error is not None and error.code() == grpc.StatusCode.DEADLINE_EXCEEDED, error
            assert "request_seconds" in error.details()
    assert "sent no request message within 3 s" in caplog.text


def test_streams_cancelled_midway_give_their_call_slots_back(tmp_path: Path) -> None:
    """Each frame stream holds one of two call slots; a client cancelling it gives the slot back."""
    configured = settings(tmp_path)
    configured.access.max_concurrent_calls = 2
    frames = messages(scene("0:1"))
    with serving(configured) as running:
        session = SessionRef.from_credentials(running.stub.CreateSession(create_request(FROZEN)))
        for _ in range(4):
            feed: queue.Queue[pb.Frame | None] = queue.Queue()
            acks = running.stub.StreamFrames(iter(feed.get, None), metadata=session.stream_metadata(), timeout=60)
            feed.put(frames[0])
            assert next(acks).accepted
            acks.cancel()
            feed.put(None)
            deadline = time.monotonic() + 10.0
            while any(listed.streaming for listed in running.stub.ListSessions(pb.ListSessionsRequest()).sessions):
                assert time.monotonic() < deadline, "the cancelled stream never ended"
                time.sleep(0.1)
        assert len(running.stub.ListSessions(pb.ListSessionsRequest(), timeout=5).sessions) == 1
