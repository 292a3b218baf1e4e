"""One HTTP listener of the server: an aiohttp application on an event loop thread of its own, behind the
listener policy (``policy.py``), the ``Host`` check, and the log rules every such listener keeps.

Blocking work (a map's decode, a metrics scrape) runs on the loop's executor, a pool of at most
``max_connections`` threads made as needed. Every answer gets ``Cache-Control: no-store`` (unless it
says otherwise: the static files), ``Referrer-Policy: no-referrer`` and ``X-Content-Type-Options:
nosniff``. What escapes a handler, the library's reports of bad requests and the event loop's own
errors are each one throttled log line, never a traceback: any client could repeat them at will.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import sys
import time
from collections.abc import Awaitable, Callable, MutableMapping
from concurrent.futures import ThreadPoolExecutor
from typing import Any

from aiohttp import web
from aiohttp.http_exceptions import HttpProcessingError

from ogserver.event_loop import EventLoop
from ogserver.http.policy import Connections, Guard, Policy
from ogserver.throttled_log import ThrottledLog

log = logging.getLogger(__name__)
_failures = ThrottledLog(log, 10.0)
_refusals = ThrottledLog(log, 10.0)
_loop_errors = ThrottledLog(log, 10.0)
HEADERS = {"Cache-Control": "no-store", "Referrer-Policy": "no-referrer", "X-Content-Type-Options": "nosniff"}
STOP_SECONDS = 1.0  # for requests being answered when the listener stops
Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


def text(status: int, body: str) -> web.Response:
    return web.Response(status=status, body=body.encode(), headers={"Content-Type": "text/plain"})


def bind(host: str, port: int) -> socket.socket:
    """A listening socket on ``host:port`` (0: any free port), its address family as the host names it."""
    host = host.strip("[]")
    family = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)[0][0]
    return socket.create_server((host, port), family=family,
                                dualstack_ipv6=family == socket.AF_INET6 and socket.has_dualstack_ipv6())


class _LibraryLog(logging.LoggerAdapter):
    """aiohttp's server log: a client's malformed request one DEBUG line, anything else one throttled line at
    its level; never a traceback."""

    def log(self, level: int, msg: object, *args: object, exc_info: object = None, **kwargs: Any) -> None:
        error = exc_info if isinstance(exc_info, BaseException) else sys.exc_info()[1] if exc_info else None
        line = f"{self.extra['name']}: {str(msg) % args if args else msg}" + (f": {error!r}" if error else "")
        if level < logging.WARNING or isinstance(error, HttpProcessingError | ConnectionError):
            log.debug("%s", line[:500])
        else:
            _failures.log(level, line[:500])


def _policy_middleware(name: str, policy: Policy) -> Callable[[web.Request, Handler], Awaitable[web.StreamResponse]]:
    @web.middleware
    async def guarded(request: web.Request, handler: Handler) -> web.StreamResponse:
        guard = Guard.of(request.transport)
        if guard is not None:
            guard.request_started()
        try:
            response = await _answer(name, policy, request, handler)
        finally:
            if guard is not None:
                guard.request_finished()
        for header, value in HEADERS.items():
            response.headers.setdefault(header, value)
        return response

    return guarded


async def _answer(name: str, policy: Policy, request: web.Request, handler: Handler) -> web.StreamResponse:
    host = request.headers.get("Host", "")
    if policy.hosts is not None and not policy.hosts.allows(host):
        _refusals.warning(f"{name}: refused a request for host {host[:100]!r}, not one of this server's names")
        return text(403, "this server answers only requests that name one of its hosts\n")
    try:
        return await handler(request)
    except web.HTTPException as refusal:  # the router's 404 and 405
        return text(refusal.status, f"{refusal.reason.lower()}\n")
    except Exception as error:
        _failures.log(logging.ERROR, f"{name}: {request.raw_path[:100]!r} failed: {error!r}")
        return text(500, "the server failed; its log says why\n")


class HttpServer:
    """``app`` served on ``host:port`` under ``policy``; ``name`` heads its log lines. The port is bound at
    once (OSError), served from ``start`` on."""

    def __init__(self, name: str, host: str, port: int, app: web.Application, policy: Policy) -> None:
        self.name = name
        self.policy = policy
        self._socket = bind(host, port)
        self.port: int = self._socket.getsockname()[1]
        app.middlewares.insert(0, _policy_middleware(name, policy))
        self._runner = web.AppRunner(app, handle_signals=False, shutdown_timeout=STOP_SECONDS, access_log=None,
                                     logger=_LibraryLog(log, {"name": name}), keepalive_timeout=policy.head_seconds)
        self._connections = Connections(policy)
        self._loop: EventLoop | None = None
        self._server: asyncio.Server | None = None

    def url(self, host: str) -> str:
        return f"{'https' if self.policy.tls else 'http'}://{host}:{self.port}/"

    def start(self) -> HttpServer:
        self._loop = EventLoop(self.name)
        self._loop.loop.set_default_executor(ThreadPoolExecutor(self.policy.max_connections,
                                                                thread_name_prefix=self.name))
        self._loop.loop.set_exception_handler(self._loop_error)
        self._loop.run(self._serve())
        return self

    async def _serve(self) -> None:
        await self._runner.setup()
        handlers = self._runner.server
        assert handlers is not None
        self._server = await asyncio.get_running_loop().create_server(
            lambda: Guard(self.name, self._connections, handlers()), sock=self._socket)

    def _loop_error(self, loop: asyncio.AbstractEventLoop, context: MutableMapping[str, Any]) -> None:
        _loop_errors.warning(f"{self.name}: {context.get('message')}: {context.get('exception')!r}")

    def loop_cpu_seconds(self) -> float:
        """The CPU seconds its event loop thread has spent (reading requests, sending answers)."""
        async def spent() -> float:
            return time.thread_time()

        return self._loop.run(spent()) if self._loop is not None else 0.0

    def stop(self) -> None:
        if self._loop is None:
            self._socket.close()
            return
        self._loop.run(self._close())
        self._loop.close()

    async def _close(self) -> None:
        assert self._server is not None
        self._server.close()
        await self._runner.cleanup()
        self._connections.close()  # those still in their TLS handshake or head
