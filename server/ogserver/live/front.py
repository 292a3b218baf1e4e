"""The Foxglove port's gate: it reads each WebSocket handshake, and then every message, before the SDK does.

The SDK's server has no hook at the handshake and no notion of who watches: it accepts any
``Origin``, asks no credential and advertises every session's topics to every client. So it listens
on a loopback address of its own (a random one in 127.0.0.0/8 where the system has them, out of reach
of a browser page that scans ports), and this front listens on the Foxglove port. It refuses an
``Origin`` the operator did not list (native clients send none), takes the web view's credentials
(``Viewers``: an API key, a session token, a client certificate under mutual TLS, or the operator's
Foxglove token, which sees everything) and refuses a wrong one with 401, counted like the web view's,
and serves TLS when given a certificate. Once admitted, it parses the WebSocket frames both ways
(``websocket.py``; permessage-deflate is taken out of the handshake it forwards, so frames stay
plain) and passes each Foxglove message through the connection's ``ChannelFilter``: the client is
shown, and may subscribe to, only the topics of sessions its credential sees. Handshakes are bounded
in size and time, client messages in size, and connections in number.
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

import grpc

from ogserver.access.transport import certificate_names
from ogserver.access.viewers import EVERYTHING, Credential, Scope, Viewers
from ogserver.errors import ServiceError
from ogserver.live.channels import ChannelFilter
from ogserver.live.websocket import CONTROL, TEXT, FrameReader, ProtocolError, frame
from ogserver.throttled_log import ThrottledLog

log = logging.getLogger(__name__)
HANDSHAKE_BYTES = 16 * 1024  # an HTTP upgrade request's head; longer ones are refused
HANDSHAKE_SECONDS = 10.0  # for TLS and the request's head together
MAX_CONNECTIONS = 64
CLIENT_MESSAGE_BYTES = 1 << 20  # a client sends only subscriptions
SERVER_MESSAGE_BYTES = 1 << 30  # the SDK's messages: images and point clouds within --view-points
CHUNK_BYTES = 256 * 1024
LOG_INTERVAL_SECONDS = 10.0
_refusals = ThrottledLog(log, LOG_INTERVAL_SECONDS)


class Refused(Exception):
    """A handshake the gate refuses: the HTTP status it is answered with, and why."""

    def __init__(self, status: int, reason: str) -> None:
        super().__init__(reason)
        self.status = status
        self.reason = reason


@dataclass(frozen=True)
class Gate:
    """Who may connect and what each sees: ``viewers`` checks a credential as the web view does; the
    ``Origin`` values allowed (none: only clients that send no Origin); the operator's ``token`` that
    sees every session ("" = none)."""

    viewers: Viewers
    origins: frozenset[str] = frozenset()
    token: str = ""

    def admit(self, head: bytes, names: list[bytes], address: str) -> Scope:
        """What this handshake's caller sees; ``Refused`` says why it may not connect."""
        target, headers = _request(head)
        origin = headers.get("origin")
        if origin is not None and origin not in self.origins:
            raise Refused(403, f"Origin {origin[:200]!r} is not one the server allows (--foxglove-origin)")
        query = parse_qs(urlsplit(target).query)
        credential = Credential(key=query.get("key", [""])[0], token=query.get("token", [""])[0],
                                certificate_names=names, address=address)
        if self.token and hmac.compare_digest(credential.token.encode(), self.token.encode()):
            return EVERYTHING
        if not credential.presented and not self.viewers.callers.open:
            raise Refused(401, "a credential is needed: ?key=API_KEY or ?token=SESSION_TOKEN")
        try:
            return self.viewers.scope(credential)
        except ServiceError as refusal:
            raise Refused(429 if refusal.code == grpc.StatusCode.RESOURCE_EXHAUSTED else 401, refusal.message) \
                from None


def _request(head: bytes) -> tuple[str, dict[str, str]]:
    """A GET request head's target and headers (names in lower case); ``Refused`` for anything else."""
    lines = head.decode("latin-1").split("\r\n")
    parts = lines[0].split(" ")
    if len(parts) != 3 or parts[0] != "GET":
        raise Refused(400, "not a WebSocket handshake")
    headers: dict[str, str] = {}
    for line in lines[1:]:
        name, colon, value = line.partition(":")
        if colon:
            headers[name.strip().lower()] = value.strip()
    return parts[1], headers


def without_extensions(head: bytes) -> bytes:
    """The handshake without its ``Sec-WebSocket-Extensions`` (permessage-deflate): frames stay plain."""
    lines = head.split(b"\r\n")
    return b"\r\n".join(line for line in lines if not line.lower().startswith(b"sec-websocket-extensions:"))


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
        except (OSError, TimeoutError, asyncio.IncompleteReadError, asyncio.LimitOverrunError):
            # a client gone, a TLS failure or an SDK that does not answer the handshake ends the connection
            pass
        finally:
            self._connections.discard(task)
            await _close(writer)

    async def _admit(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), HANDSHAKE_SECONDS)
        except (TimeoutError, asyncio.LimitOverrunError, asyncio.IncompleteReadError):
            return
        peer = writer.get_extra_info("peername")
        address = peer[0] if peer else ""
        names = certificate_names(writer.get_extra_info("peercert")) if self._tls else []
        try:
            scope = self._gate.admit(head, names, address)
        except Refused as refused:
            _refusals.warning(f"Foxglove port: refused {address or 'a client'}: {refused.reason}")
            body = f"{refused.reason}\n".encode()
            writer.write(b"HTTP/1.1 %d Refused\r\nContent-Type: text/plain\r\nConnection: close\r\n"
                         b"Content-Length: %d\r\n\r\n%s" % (refused.status, len(body), body))
            await writer.drain()
            return
        inner_reader, inner_writer = await asyncio.open_connection(*self._inner, limit=CHUNK_BYTES)
        try:
            inner_writer.write(without_extensions(head))
            answer = await asyncio.wait_for(inner_reader.readuntil(b"\r\n\r\n"), HANDSHAKE_SECONDS)
            writer.write(answer)
            if not answer.startswith(b"HTTP/1.1 101"):  # the SDK's refusal (a subprotocol it does not speak)
                await _pipe(inner_reader, writer)
                return
            channels = ChannelFilter(lambda session_id: scope.sees(self._gate.viewers.registry, session_id))
            # Each direction closes its sink when its source ends, which ends the other one.
            await asyncio.gather(_from_client(reader, inner_writer, writer, channels),
                                 _from_server(inner_reader, writer, channels), return_exceptions=True)
        finally:
            await _close(inner_writer)


async def _from_client(client: asyncio.StreamReader, server: asyncio.StreamWriter, answers: asyncio.StreamWriter,
                       channels: ChannelFilter) -> None:
    """The client's messages to the server, filtered; the statuses for what was dropped to ``answers``."""
    frames = FrameReader(client, masked=True, max_bytes=CLIENT_MESSAGE_BYTES)
    try:
        while True:
            message = await frames.message()
            if message.opcode in CONTROL:
                server.write(frame(message.opcode, message.payload, masked=True))
            else:
                forwarded, statuses = channels.from_client(message.opcode, message.payload)
                if forwarded is not None:
                    server.write(frame(message.opcode, forwarded, masked=True))
                for status in statuses:
                    answers.write(frame(TEXT, status, masked=False))
                await answers.drain()
            await server.drain()
    except ProtocolError as error:
        _refusals.warning(f"Foxglove port: ended a connection: {error}")
    finally:
        server.close()  # the other direction then ends too


async def _from_server(server: asyncio.StreamReader, client: asyncio.StreamWriter, channels: ChannelFilter) -> None:
    """The server's messages to the client, filtered."""
    frames = FrameReader(server, masked=False, max_bytes=SERVER_MESSAGE_BYTES)
    try:
        while True:
            message = await frames.message()
            shown = message.payload if message.opcode in CONTROL else channels.from_server(message.opcode,
                                                                                          message.payload)
            if shown is not None:
                client.write(frame(message.opcode, shown, masked=False))
                await client.drain()
    finally:
        client.close()  # the other direction then ends too


async def _pipe(source: asyncio.StreamReader, sink: asyncio.StreamWriter) -> None:
    while data := await source.read(CHUNK_BYTES):
        sink.write(data)
        await sink.drain()


async def _close(writer: asyncio.StreamWriter) -> None:
    writer.close()
    with contextlib.suppress(OSError, TimeoutError):
        await asyncio.wait_for(writer.wait_closed(), HANDSHAKE_SECONDS)
