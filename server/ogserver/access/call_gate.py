"""Every call passes here. ogapi.v1.Mapping calls are held to ``max_concurrent_calls``, their status
observed, and served from the event loop (``sync_calls.py``); every unary call must send its request
within ``request_seconds``, and a response stream's client take each message within ``response_seconds``.

The server is grpc.aio: a call waiting for its client costs no thread. Synchronous mapping calls run
in a thread pool with ``HEADROOM`` threads beyond the limit, for refusing calls over it; health
checks and reflection are coroutines in the event loop, so they answer whatever the mapping calls
and the clients that send nothing hold.
"""

from __future__ import annotations

import threading
from collections.abc import Awaitable, Callable, Iterator
from concurrent.futures import Executor
from contextlib import contextmanager
from typing import Any

import grpc
from grpc import aio
from ogapi import SERVICE_NAME

from ogserver.access.sync_calls import SyncCalls

HEADROOM = 8
Observer = Callable[[str, grpc.StatusCode], None]  # method name, final status


class _Recorded:
    """A servicer's context that remembers the status the call was ended with."""

    def __init__(self, context: Any) -> None:
        self._context = context
        self.ended_with: grpc.StatusCode | None = None

    def abort(self, code: grpc.StatusCode, details: str = "") -> None:
        self.ended_with = code
        self._context.abort(code, details)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._context, name)


class CallGate(aio.ServerInterceptor):
    def __init__(self, limit: int, observe: Observer, request_seconds: float, pool: Executor,
                 response_seconds: float = 0.0) -> None:
        self.limit = limit
        self._slots = threading.BoundedSemaphore(limit)
        self._observe = observe
        self._sync = SyncCalls(request_seconds, pool, response_seconds)

    async def intercept_service(
        self, continuation: Callable[[grpc.HandlerCallDetails], Awaitable[grpc.RpcMethodHandler]],
        details: grpc.HandlerCallDetails,
    ) -> grpc.RpcMethodHandler:
        handler = await continuation(details)
        if handler is None:
            return handler
        if details.method.startswith(f"/{SERVICE_NAME}/"):
            return self._sync.serve(self._gated(handler, details.method.rsplit("/", 1)[1]), details.method)
        if not handler.request_streaming and not handler.response_streaming:
            return self._sync.with_deadline(handler, details.method)
        return handler

    def _gated(self, handler: grpc.RpcMethodHandler, method: str) -> grpc.RpcMethodHandler:
        kind = ("stream" if handler.request_streaming else "unary") + "_" + (
            "stream" if handler.response_streaming else "unary")
        behaviour = getattr(handler, kind)
        wrapped = self._streaming(behaviour, method) if handler.response_streaming else self._unary(behaviour, method)
        return handler._replace(**{kind: wrapped})

    def _unary(self, behaviour: Callable[..., Any], method: str) -> Callable[..., Any]:
        def call(request: Any, context: grpc.ServicerContext) -> Any:
            recorded = _Recorded(context)
            with self._admitted(method, recorded):
                return behaviour(request, recorded)
        return call

    def _streaming(self, behaviour: Callable[..., Any], method: str) -> Callable[..., Iterator[Any]]:
        def call(request: Any, context: grpc.ServicerContext) -> Iterator[Any]:
            recorded = _Recorded(context)
            with self._admitted(method, recorded):
                yield from behaviour(request, recorded)
        return call

    @contextmanager
    def _admitted(self, method: str, context: _Recorded) -> Iterator[None]:
        if not self._slots.acquire(blocking=False):
            self._observe(method, grpc.StatusCode.RESOURCE_EXHAUSTED)
            context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED,
                          f"the server is at its limit of {self.limit} concurrent calls; retry later")
        code = grpc.StatusCode.OK
        try:
            yield
        except GeneratorExit:  # the client went away in the middle of a response stream
            code = grpc.StatusCode.CANCELLED
            raise
        except BaseException:
            code = context.ended_with or grpc.StatusCode.UNKNOWN
            raise
        finally:
            self._slots.release()
            self._observe(method, code)
