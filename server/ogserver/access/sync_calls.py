"""Synchronous servicer methods served from grpc.aio's event loop, and every unary call's request deadline.

grpc.aio runs a synchronous handler in its thread pool, but a synchronous response stream there
feeds a one-place queue that nobody drains once the client goes away: the thread blocks for ever
and the call's slot with it. So the mapping methods are served here as coroutines: a unary call
reads its request in the event loop (no thread waits for a client that sends nothing), within
``request_seconds`` of its headers (DEADLINE_EXCEEDED past it, one throttled WARNING line in the
log); the method then runs in the pool; a response stream is taken from it one message at a
time, and closed when the call ends early, so its ``finally`` blocks run. Each response message must be
taken by the client (HTTP/2 flow control) within ``response_seconds``, else the call ends
DEADLINE_EXCEEDED: a client that opens response streams and reads nothing would otherwise hold their
call slots for as long as its connection stays open.
"""

from __future__ import annotations

import asyncio
import inspect
import logging
from collections.abc import AsyncIterator, Callable, Iterator
from concurrent.futures import Executor
from typing import Any

import grpc
from grpc import aio

from ogserver.throttled_log import ThrottledLog

log = logging.getLogger(__name__)
_END = object()


class BlockingContext:
    """The aio context as a synchronous servicer uses it, from a pool thread."""

    def __init__(self, context: aio.ServicerContext, loop: asyncio.AbstractEventLoop) -> None:
        self._context = context
        self._loop = loop

    def abort(self, code: grpc.StatusCode, details: str = "") -> None:
        asyncio.run_coroutine_threadsafe(self._context.abort(code, details), self._loop).result()

    def add_callback(self, callback: Callable[[], None]) -> None:
        self._context.add_done_callback(lambda _: callback())

    def __getattr__(self, name: str) -> Any:
        return getattr(self._context, name)


class SyncCalls:
    """One per server, so that each server's log is throttled on its own."""

    def __init__(self, request_seconds: float, pool: Executor, response_seconds: float = 0.0) -> None:
        self.request_seconds = request_seconds
        self.response_seconds = response_seconds
        self._pool = pool
        self._log = ThrottledLog(log, 10.0)

    def serve(self, handler: grpc.RpcMethodHandler, method: str) -> grpc.RpcMethodHandler:
        """``handler``, whose behaviour is synchronous, as a coroutine handler."""
        kind = ("stream" if handler.request_streaming else "unary") + "_" + (
            "stream" if handler.response_streaming else "unary")
        behaviour = getattr(handler, kind)

        async def arguments(context: aio.ServicerContext) -> tuple[Any, BlockingContext]:
            loop = asyncio.get_running_loop()
            if handler.request_streaming:
                return _requests(context, loop), BlockingContext(context, loop)
            return await self._request(context, method), BlockingContext(context, loop)

        async def unary(_: Any, context: aio.ServicerContext) -> Any:
            request, blocking = await arguments(context)
            return await asyncio.get_running_loop().run_in_executor(self._pool, behaviour, request, blocking)

        async def streaming(_: Any, context: aio.ServicerContext) -> None:
            request, blocking = await arguments(context)
            responses = await asyncio.get_running_loop().run_in_executor(self._pool, behaviour, request, blocking)
            async for response in self._stepped(responses):
                await self._write(context, response, method)

        factory = grpc.stream_stream_rpc_method_handler if handler.response_streaming \
            else grpc.stream_unary_rpc_method_handler
        return factory(streaming if handler.response_streaming else unary,
                       request_deserializer=handler.request_deserializer,
                       response_serializer=handler.response_serializer)

    def with_deadline(self, handler: grpc.RpcMethodHandler, method: str) -> grpc.RpcMethodHandler:
        """``handler`` (unary-unary, a coroutine) reading its request within ``request_seconds``."""
        behaviour = handler.unary_unary

        async def call(_: Any, context: aio.ServicerContext) -> Any:
            return await behaviour(await self._request(context, method), context)

        return grpc.stream_unary_rpc_method_handler(call, request_deserializer=handler.request_deserializer,
                                                    response_serializer=handler.response_serializer)

    async def _request(self, context: aio.ServicerContext, method: str) -> Any:
        try:
            request = await asyncio.wait_for(context.read(), self.request_seconds or None)
        except TimeoutError:
            self._log.warning(f"{method} from {context.peer()} sent no request message within "
                              f"{self.request_seconds:g} s; ended")
            await context.abort(grpc.StatusCode.DEADLINE_EXCEEDED,
                                f"no request message within {self.request_seconds:g} s (the server's request_seconds)")
        if request is aio.EOF:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "the call ended without a request message")
        return request

    async def _write(self, context: aio.ServicerContext, response: Any, method: str) -> None:
        try:
            await asyncio.wait_for(context.write(response), self.response_seconds or None)
        except TimeoutError:
            self._log.warning(f"{method} to {context.peer()}: the client took no response message within "
                              f"{self.response_seconds:g} s; ended")
            await context.abort(grpc.StatusCode.DEADLINE_EXCEEDED,
                                f"no response message taken within {self.response_seconds:g} s "
                                f"(the server's response_seconds)")

    async def _stepped(self, responses: Iterator[Any]) -> AsyncIterator[Any]:
        """``responses`` one at a time in the pool; closed once the step in flight returns if the call ends."""
        step = None
        try:
            while True:
                step = self._pool.submit(next, responses, _END)
                response = await asyncio.wrap_future(step)
                if response is _END:
                    return
                yield response
        finally:
            if step is not None:
                step.add_done_callback(lambda _: _close(responses))


def _close(responses: Iterator[Any]) -> None:
    if inspect.isgenerator(responses):
        responses.close()


def _requests(context: aio.ServicerContext, loop: asyncio.AbstractEventLoop) -> Iterator[Any]:
    """The client's stream, read from a thread."""
    while True:
        message = asyncio.run_coroutine_threadsafe(context.read(), loop).result()
        if message is aio.EOF:
            return
        yield message
