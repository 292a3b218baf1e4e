"""Every ogapi.v1.Mapping call passes here: held to ``max_concurrent_calls`` and its status observed.

Health checks and reflection are not counted, and the server's thread pool has ``HEADROOM``
threads beyond the limit for them (and for refusing calls over it), so a server whose mapping
calls are all taken, even by clients that send nothing, still answers its health check.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import grpc
from ogapi import SERVICE_NAME

HEADROOM = 8
Observer = Callable[[str, grpc.StatusCode], None]  # method name, final status


class CallGate(grpc.ServerInterceptor):
    def __init__(self, limit: int, observe: Observer) -> None:
        self.limit = limit
        self._slots = threading.BoundedSemaphore(limit)
        self._observe = observe

    def intercept_service(self, continuation: Callable[..., Any], details: grpc.HandlerCallDetails) -> Any:
        handler = continuation(details)
        if handler is None or not details.method.startswith(f"/{SERVICE_NAME}/"):
            return handler
        method = details.method.rsplit("/", 1)[1]
        kind = ("stream" if handler.request_streaming else "unary") + "_" + (
            "stream" if handler.response_streaming else "unary")
        behaviour = getattr(handler, kind)
        wrapped = self._streaming(behaviour, method) if handler.response_streaming else self._unary(behaviour, method)
        return handler._replace(**{kind: wrapped})

    def _unary(self, behaviour: Callable[..., Any], method: str) -> Callable[..., Any]:
        def call(request: Any, context: grpc.ServicerContext) -> Any:
            with self._admitted(method, context):
                return behaviour(request, context)
        return call

    def _streaming(self, behaviour: Callable[..., Any], method: str) -> Callable[..., Iterator[Any]]:
        def call(request: Any, context: grpc.ServicerContext) -> Iterator[Any]:
            with self._admitted(method, context):
                yield from behaviour(request, context)
        return call

    @contextmanager
    def _admitted(self, method: str, context: grpc.ServicerContext) -> Iterator[None]:
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
            code = context.code() or grpc.StatusCode.UNKNOWN
            raise
        finally:
            self._slots.release()
            self._observe(method, code)
