"""What every HTTP listener of the server holds its clients to, below the HTTP library: connections in
number, in total and per client address, and in time.

A timeout per read does not bound a request: a client sending one header byte every few seconds keeps
its connection, and enough such connections take a server from everyone (slowloris). Here a
connection's TLS handshake and first request head must arrive within ``head_seconds`` of its accept,
in all, and each later request's head within ``head_seconds`` of its first byte; an idle kept-alive
connection is closed after ``head_seconds`` (the library's keep-alive timeout). A response that the
client takes nothing of for ``stall_seconds`` ends its connection. One address holds at most
``per_address`` connections, so a single client cannot take them all.

``Guard`` is the asyncio protocol the listening socket sees: it counts and times the connection and
passes everything else to the library's own protocol (aiohttp's ``RequestHandler``), over TLS where
the policy has a context (``loop.start_tls``, so the handshake runs under the same deadline).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import ssl
import struct
from dataclasses import dataclass

from ogserver.access.shares import Shares
from ogserver.throttled_log import ThrottledLog
from ogserver.web.hosts import HostPolicy

log = logging.getLogger(__name__)
_refusals = ThrottledLog(log, 10.0)

HEAD_SECONDS = 10.0
PER_ADDRESS = 16


@dataclass(frozen=True)
class Policy:
    """One listener's limits; ``hosts`` None answers any ``Host``, ``tls`` None speaks plain HTTP."""

    max_connections: int = 64
    per_address: int = PER_ADDRESS
    head_seconds: float = HEAD_SECONDS
    stall_seconds: float = HEAD_SECONDS
    hosts: HostPolicy | None = None
    tls: ssl.SSLContext | None = None


class Connections:
    """The connections open, in all and per client address (used on the listener's event loop only)."""

    def __init__(self, policy: Policy) -> None:
        self.policy = policy
        self.guards: set[Guard] = set()
        self._per_address = Shares(policy.per_address)

    def admit(self, guard: Guard, address: str) -> str | None:
        """Why a new connection from ``address`` is refused, else None (and it is counted)."""
        if len(self.guards) >= self.policy.max_connections:
            return f"refused a connection, {self.policy.max_connections} are open"
        if not self._per_address.take(address):
            return f"refused a connection from {address}, which has {self.policy.per_address} open"
        self.guards.add(guard)
        return None

    def close(self) -> None:
        """Ends every connection open."""
        for guard in list(self.guards):
            guard.abort()

    def release(self, guard: Guard, address: str) -> None:
        self.guards.discard(guard)
        self._per_address.give_back(address)


class Guard(asyncio.Protocol):
    """One accepted connection: counted, timed, and passed on to ``handler``, the library's protocol."""

    def __init__(self, name: str, connections: Connections, handler: asyncio.Protocol) -> None:
        self._name = name
        self._connections = connections
        self._policy = connections.policy
        self._handler = handler
        self._raw: asyncio.Transport | None = None
        self._address: str | None = None  # set while counted
        self._passed = False  # the handler has its transport
        self._deadline: asyncio.TimerHandle | None = None
        self._stall: asyncio.TimerHandle | None = None
        self._requests = 0  # requests being answered
        self._early = False  # bytes came in while one was
        self._before: list[bytes] = []  # bytes come before the handler has its transport
        self._securing: asyncio.Task | None = None  # the TLS handshake (the loop keeps only a weak reference)

    @staticmethod
    def of(transport: asyncio.BaseTransport | None) -> Guard | None:
        """The guard of a request's transport (plain or TLS), None once the connection is gone."""
        protocol = transport.get_protocol() if transport is not None else None
        return protocol if isinstance(protocol, Guard) else None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self._raw = transport
        peer = transport.get_extra_info("peername")
        address = str(peer[0]) if peer else "?"
        refusal = self._connections.admit(self, address)
        if refusal is not None:
            _refusals.warning(f"{self._name}: {refusal}")
            cut(transport)
            return
        self._address = address
        self._arm(self._policy.head_seconds)  # the TLS handshake and the first request's head, in all
        if self._policy.tls is None:
            self._pass(transport)
        else:
            transport.pause_reading()  # the ClientHello is for the TLS layer
            self._securing = asyncio.get_running_loop().create_task(self._secure(transport))

    async def _secure(self, transport: asyncio.Transport) -> None:
        loop = asyncio.get_running_loop()
        assert self._policy.tls is not None and self._deadline is not None
        try:
            secured = await loop.start_tls(transport, self, self._policy.tls, server_side=True,
                                           ssl_handshake_timeout=max(self._deadline.when() - loop.time(), 0.1))
        except (OSError, TimeoutError, ConnectionError):  # no TLS, no trusted certificate, or too slow: closed
            secured = None
        if secured is None or self._address is None:  # the TLS layer tells no connection lost in its handshake
            self._release()
        else:
            self._pass(secured)

    def _pass(self, transport: asyncio.BaseTransport) -> None:
        self._passed = True
        self._handler.connection_made(transport)
        early, self._before = b"".join(self._before), []
        if early:  # what the TLS layer decrypted before start_tls returned
            self._handler.data_received(early)

    def _release(self) -> None:
        """The connection no longer counts (once, however its end is told)."""
        self._disarm()
        if self._stall is not None:
            self._stall.cancel()
        if self._address is not None:
            self._connections.release(self, self._address)
            self._address = None

    def _arm(self, seconds: float) -> None:
        self._disarm()
        self._deadline = asyncio.get_running_loop().call_later(seconds, self._expire)

    def _disarm(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None

    def _expire(self) -> None:
        self._deadline = None
        self.abort()

    def _stalled(self) -> None:
        self._stall = None
        self.abort(reset=True)

    def abort(self, reset: bool = False) -> None:
        if self._raw is not None:
            cut(self._raw, reset)  # connection_lost follows, on the handler too

    def request_started(self) -> None:
        """A request's head is in: its deadline is met."""
        self._requests += 1
        self._disarm()

    def request_finished(self) -> None:
        self._requests -= 1
        if not self._requests and self._early and self._deadline is None:  # the next head began meanwhile
            self._early = False
            self._arm(self._policy.head_seconds)

    def data_received(self, data: bytes) -> None:
        if self._requests:
            self._early = True
        elif self._deadline is None:  # the first bytes of the next request: its head has head_seconds
            self._arm(self._policy.head_seconds)
        if self._passed:
            self._handler.data_received(data)
        else:
            self._before.append(data)

    def eof_received(self) -> bool | None:
        return self._handler.eof_received() if self._passed else None

    def pause_writing(self) -> None:
        """The client takes nothing in: it has ``stall_seconds`` to take some."""
        if self._stall is None:
            self._stall = asyncio.get_running_loop().call_later(self._policy.stall_seconds, self._stalled)
        if self._passed:
            self._handler.pause_writing()

    def resume_writing(self) -> None:
        if self._stall is not None:
            self._stall.cancel()
            self._stall = None
        if self._passed:
            self._handler.resume_writing()

    def connection_lost(self, exc: Exception | None) -> None:
        self._release()
        if self._passed:
            self._passed = False
            with contextlib.suppress(Exception):  # the handler's own cleanup; the connection is gone either way
                self._handler.connection_lost(exc)



def cut(transport: asyncio.Transport, reset: bool = False) -> None:
    """Ends a connection at once: its end of stream sent first so that the client reads one, or with
    ``reset`` a reset, so that the system does not go on sending what is left in its buffers either."""
    with contextlib.suppress(OSError, RuntimeError):  # already closing
        if reset:
            transport.get_extra_info("socket").setsockopt(socket.SOL_SOCKET, socket.SO_LINGER,
                                                          struct.pack("ii", 1, 0))
        elif transport.can_write_eof():
            transport.write_eof()
    transport.abort()
