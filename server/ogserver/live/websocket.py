"""WebSocket framing (RFC 6455) as the Foxglove port's front reads it: frames in, whole messages out.

The front looks inside every message both ways, so it parses frames itself: the header, the 16- and
64-bit lengths, the client's mask, fragmented messages (reassembled, their control frames passed on
between the fragments), and ping, pong and close. Messages are written again as single frames,
masked toward the server as a client's must be. Extensions (permessage-deflate) are kept out of the
handshake, so every frame is plain; a frame that sets a reserved bit is a protocol error.
"""

from __future__ import annotations

import asyncio
import os
import struct
from dataclasses import dataclass

CONTINUATION, TEXT, BINARY, CLOSE, PING, PONG = 0x0, 0x1, 0x2, 0x8, 0x9, 0xA
DATA = (TEXT, BINARY)
CONTROL = (CLOSE, PING, PONG)


class ProtocolError(Exception):
    """A frame that breaks RFC 6455 (or the front's size bound): the connection is ended."""


@dataclass(frozen=True)
class Message:
    """A whole data message (``TEXT`` or ``BINARY``), or one control frame."""

    opcode: int
    payload: bytes


def unmask(payload: bytes, mask: bytes) -> bytes:
    """``payload`` XOR the repeated 4-byte ``mask`` (masking and unmasking are the same)."""
    if not payload:
        return payload
    repeated = (mask * (len(payload) // 4 + 1))[: len(payload)]
    return (int.from_bytes(payload, "little") ^ int.from_bytes(repeated, "little")).to_bytes(len(payload), "little")


def frame(opcode: int, payload: bytes, masked: bool) -> bytes:
    """One final frame carrying ``payload``; ``masked`` with a fresh key (a client's frames must be)."""
    length = len(payload)
    if length < 126:
        head = struct.pack("!BB", 0x80 | opcode, length | (0x80 if masked else 0))
    elif length < 1 << 16:
        head = struct.pack("!BBH", 0x80 | opcode, 126 | (0x80 if masked else 0), length)
    else:
        head = struct.pack("!BBQ", 0x80 | opcode, 127 | (0x80 if masked else 0), length)
    if not masked:
        return head + payload
    mask = os.urandom(4)
    return head + mask + unmask(payload, mask)


class FrameReader:
    """Reads a peer's frames: ``masked`` says whether they must be masked (a client's) or must not be (a
    server's); a message longer than ``max_bytes`` is a protocol error."""

    def __init__(self, reader: asyncio.StreamReader, masked: bool, max_bytes: int) -> None:
        self._reader = reader
        self._masked = masked
        self._max_bytes = max_bytes
        self._parts: list[bytes] = []  # a fragmented message so far
        self._size = 0  # its bytes
        self._opcode = 0  # its opcode

    async def message(self) -> Message:
        """The next whole data message or control frame; IncompleteReadError when the peer is gone."""
        while True:
            fin, opcode, payload = await self._frame()
            if opcode in CONTROL:
                if not fin or len(payload) > 125:
                    raise ProtocolError("a control frame fragmented or over 125 bytes")
                return Message(opcode, payload)
            if opcode == CONTINUATION:
                if not self._parts:
                    raise ProtocolError("a continuation frame outside a message")
            elif opcode in DATA:
                if self._parts:
                    raise ProtocolError("a new message inside a fragmented one")
                self._opcode = opcode
            else:
                raise ProtocolError(f"unknown opcode {opcode:#x}")
            self._parts.append(payload)
            self._size += len(payload)
            if self._size > self._max_bytes:
                raise ProtocolError(f"a message over {self._max_bytes} bytes")
            if fin:
                whole, self._parts, self._size = b"".join(self._parts), [], 0
                return Message(self._opcode, whole)

    async def _frame(self) -> tuple[bool, int, bytes]:
        first, second = await self._reader.readexactly(2)
        if first & 0x70:
            raise ProtocolError("a reserved bit is set (no extension was agreed)")
        if bool(second & 0x80) != self._masked:
            raise ProtocolError("a client frame unmasked, or a server frame masked")
        length = second & 0x7F
        if length == 126:
            (length,) = struct.unpack("!H", await self._reader.readexactly(2))
        elif length == 127:
            (length,) = struct.unpack("!Q", await self._reader.readexactly(8))
        if length > self._max_bytes:
            raise ProtocolError(f"a frame over {self._max_bytes} bytes")
        mask = await self._reader.readexactly(4) if self._masked else b""
        payload = await self._reader.readexactly(length)
        return bool(first & 0x80), first & 0x0F, unmask(payload, mask) if mask else payload
