"""The Foxglove port's gate: it reads each WebSocket handshake before the Foxglove SDK sees it.

The SDK's server has no hook at the handshake: it accepts any ``Origin`` and no credential. So it
listens on a loopback address of its own (a random one in 127.0.0.0/8 where the system has them,
out of reach of a browser page that scans ports), and this front listens on the Foxglove port:
it refuses an ``Origin`` the operator did not list (native clients send none), requires the secret
``token`` in the URL when one is set, serves TLS when given a certificate, then passes the bytes
both ways unchanged. Handshakes are bounded in size and time, and connections in number.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import logging
import random
import socket
import ssl
import threading
from dataclasses import dataclass
from urllib.parse import parse_qs, urlsplit

from ogserver.throttled_log import ThrottledLog

log = logging.getLogger(__name__)
HANDSHAKE_BYTES = 16 * 1024  # an HTTP upgrade request's head; longer ones are refused
HANDSHAKE_SECONDS = 10.0  # for TLS and the request's head together
MAX_CONNECTIONS = 64
CHUNK_BYTES = 256 * 1024
LOG_INTERVAL_SECONDS = 10.0
_refusals = ThrottledLog(log, LOG_INTERVAL_SECONDS)


@dataclass(frozen=True)
class Gate:
    """Who may connect: the ``Origin`` values allowed (none: only clients that send no Origin), and the
    secret the URL's ``token`` parameter must carry ("" = none asked)."""

    origins: frozenset[str] = frozenset()
    token: str = ""

    def refusal(self, head: bytes) -> str | None:
        """Why this handshake is refused, or None."""
        lines = head.decode("latin-1").split("\r\n")
        parts = lines[0].split(" ")
        if len(parts) != 3 or parts[0] != "GET":
            return "not a WebSocket handshake"
        headers: dict[str, str] = {}
        for line in lines[1:]:
            name, colon, value = line.partition(":")
            if colon:
                headers[name.strip().lower()] = value.strip()
        origin = headers.get("origin")
        if origin is not None and origin not in self.origins:
            return f"Origin {origin[:200]!r} is not one the server allows (--foxglove-origin)"
        if self.token:
            offered = parse_qs(urlsplit(parts[1]).query).get("token", [""])[0]
            if not hmac.compare_digest(offered.encode(), self.token.encode()):
                return "the URL's token is missing or wrong"
        return None


def loopback_host() -> str:
    """A random address in 127.0.0.0/8 where it can be bound (Linux), else 127.0.0.1."""
    host = f"127.{random.randrange(256)}.{random.randrange(256)}.{random.randrange(1, 255)}"
    try:
        with socket.socket() as probe:
            probe.bind((host, 0))
    except OSError:
        return "127.0.0.1"
    return host


class Front:
    """The listening port in front of the SDK's server at ``inner``, on a thread with its own event loop."""

    def __init__(self, host: str, port: int, inner: tuple[str, int], gate: Gate,
                 tls: ssl.SSLContext | None) -> None:
        self._inner = inner
        self._gate = gate
        self._tls = tls
        self._loop = asyncio.new_event_loop()
        self._connections: set[asyncio.Task] = set()
        try:
            self._server = self._loop.run_until_complete(asyncio.start_server(
                self._serve, host, port, ssl=tls, ssl_handshake_timeout=HANDSHAKE_SECONDS if tls else None,
                limit=HANDSHAKE_BYTES))
        except OSError:
            self._loop.close()
            raise
        self.port: int = self._server.sockets[0].getsockname()[1]
        self._thread = threading.Thread(target=self._loop.run_forever, name="foxglove-front", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        async def close() -> None:
            self._server.close()
            for task in list(self._connections):
                task.cancel()
            await asyncio.gather(*self._connections, return_exceptions=True)

        with contextlib.suppress(TimeoutError):  # connections that do not close in time are dropped with the loop
            asyncio.run_coroutine_threadsafe(close(), self._loop).result(2 * HANDSHAKE_SECONDS)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join()
        self._loop.close()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        if len(self._connections) >= MAX_CONNECTIONS:
            _refusals.warning(f"Foxglove port: refused a connection, {MAX_CONNECTIONS} are open")
            await _close(writer)
            return
        self._connections.add(task)
        try:
            await self._admit(reader, writer)
        except (OSError, asyncio.IncompleteReadError):  # a client gone or a TLS failure ends its connection
            pass
        finally:
            self._connections.discard(task)
            await _close(writer)

    async def _admit(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), HANDSHAKE_SECONDS)
        except (TimeoutError, asyncio.LimitOverrunError, asyncio.IncompleteReadError):
            return
        refusal = self._gate.refusal(head)
        if refusal is not None:
            peer = writer.get_extra_info("peername")
            _refusals.warning(f"Foxglove port: refused {peer[0] if peer else 'a client'}: {refusal}")
            body = f"{refusal}\n".encode()
            writer.write(b"HTTP/1.1 403 Forbidden\r\nContent-Type: text/plain\r\nConnection: close\r\n"
                         b"Content-Length: %d\r\n\r\n%s" % (len(body), body))
            await writer.drain()
            return
        inner_reader, inner_writer = await asyncio.open_connection(*self._inner)
        try:
            inner_writer.write(head)
            # Each pipe closes its sink when its source ends, which ends the other one.
            await asyncio.gather(_pipe(reader, inner_writer), _pipe(inner_reader, writer), return_exceptions=True)
        finally:
            await _close(inner_writer)


async def _pipe(source: asyncio.StreamReader, sink: asyncio.StreamWriter) -> None:
    try:
        while data := await source.read(CHUNK_BYTES):
            sink.write(data)
            await sink.drain()
    finally:
        sink.close()  # the other direction then ends too


async def _close(writer: asyncio.StreamWriter) -> None:
    writer.close()
    with contextlib.suppress(OSError, TimeoutError):
        await asyncio.wait_for(writer.wait_closed(), HANDSHAKE_SECONDS)
