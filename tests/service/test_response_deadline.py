"""A response stream whose client takes no message ends within ``response_seconds``, closing the stream on
the server's side: unread GetSnapshot calls once held every call slot for as long as their connections
stayed open."""

from __future__ import annotations

import asyncio
import threading
from concurrent.futures import ThreadPoolExecutor

import grpc
import pytest
from ogserver.access.sync_calls import SyncCalls


class Aborted(Exception):
    pass


class UnreadClient:
    """An aio servicer context whose client sent its request and takes no response message."""

    def __init__(self, request: bytes) -> None:
        self._request = request
        self.aborted: tuple[grpc.StatusCode, str] | None = None

    async def read(self) -> bytes:
        return self._request

    async def write(self, message: bytes) -> None:
        await asyncio.Event().wait()  # HTTP/2 flow control: the client's window stays shut

    async def abort(self, code: grpc.StatusCode, details: str = "") -> None:
        self.aborted = (code, details)
        raise Aborted

    def peer(self) -> str:
        return "ipv4:127.0.0.1:1"

    def add_done_callback(self, callback) -> None:
        pass


def test_a_response_the_client_never_takes_ends_the_call_and_closes_the_stream() -> None:
    closed = threading.Event()

    def responses(request: bytes, context: object):
        try:
            while True:
                yield b"snapshot chunk"
        finally:
            closed.set()

    handler = grpc.unary_stream_rpc_method_handler(responses)
    context = UnreadClient(b"request")
    with ThreadPoolExecutor(2) as pool:
        served = SyncCalls(1.0, pool, response_seconds=0.2).serve(handler, "/ogapi.v1.Mapping/GetSnapshot")
        with pytest.raises(Aborted):
            asyncio.run(asyncio.wait_for(served.stream_stream(None, context), 5))
        assert closed.wait(5), "the servicer's stream was closed, its finally blocks run"
    assert context.aborted is not None and context.aborted[0] == grpc.StatusCode.DEADLINE_EXCEEDED
    assert "response_seconds" in context.aborted[1]
