"""Every call passes here. ogapi.v1.Mapping calls are held to ``max_concurrent_calls``, their status
observed, and served from the event loop (``sync_calls.py``); every unary call must send its request
within ``request_seconds``, and a response stream's client take each message within ``response_seconds``.
One caller (its API key, else its client certificate, else its address) holds at most
``max_calls_per_caller`` of the slots, so one tenant's calls cannot refuse every other tenant's.

The server is grpc.aio: a call waiting for its client costs no thread. Synchronous mapping calls run
in a thread pool with ``HEADROOM`` threads beyond the limit, for refusing calls over it; health
checks and reflection are coroutines in the event loop, so they answer whatever the mapping calls
and the clients that send nothing hold.
"""

from __future__ import annotations

import hashlib
import threading
from collections.abc import Awaitable, Callable, Iterator
from concurrent.futures import Executor
from contextlib import contextmanager
from typing import Any

import grpc
from grpc import aio
from ogapi import API_KEY_METADATA_KEY, SERVICE_NAME

from ogserver.access.shares import Shares
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
                 response_seconds: float = 0.0, per_caller: int = 0) -> None:
        self.limit = limit
        self.per_caller = per_caller  # 0: no share, only the limit
        self._slots = threading.BoundedSemaphore(limit)
        self._held = Shares(per_caller)  # slots held per caller
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
        caller = caller_of(context)
        if not self._held.take(caller):
            self._observe(method, grpc.StatusCode.RESOURCE_EXHAUSTED)
            context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED,
                          f"this caller holds its share of {self.per_caller} concurrent calls (the server's "
                          f"max_calls_per_caller); retry when one ends")
        try:
            with self._slot(method, context):
                yield
        finally:
            self._held.give_back(caller)

    @contextmanager
    def _slot(self, method: str, context: _Recorded) -> Iterator[None]:
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


def caller_of(context: Any) -> str:
    """Who a call's slot counts against: its API key (hashed; unchecked here, a wrong one is refused later and
    counts only against itself), else its client certificate's name, else its address without the port."""
    for key, value in context.invocation_metadata() or ():
        if key == API_KEY_METADATA_KEY:
            return "key:" + hashlib.sha256(str(value).encode()).hexdigest()[:16]
    names = (context.auth_context() or {}).get("x509_common_name")
    if names:
        return "cert:" + names[0].decode(errors="replace")
    peer = context.peer() or ""
    return "address:" + peer.rsplit(":", 1)[0]
