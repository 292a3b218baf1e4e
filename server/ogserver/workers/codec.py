"""The values the server and its worker processes exchange, as bytes, without pickle.

A message is a JSON header and binary blobs: bytes, numpy arrays and protobuf messages travel as
blobs (a client's frame or snapshot crosses as the protobuf bytes the front already parsed, and the
worker parses them again with protobuf); everything else is JSON. Only the types named here can be
built on the way back in: plain values, tuples, paths, status codes, the protobuf messages in
``MESSAGES``, the dataclasses in ``DATACLASSES`` and refusals (``ServiceError``). Unlike pickle, reading a
message never runs code a message chooses.

On the wire each message is an 8-byte length and then the message, so a stream socket carries them
one after another.
"""

from __future__ import annotations

import dataclasses
import json
import socket
import struct
from pathlib import Path
from typing import Any

import grpc
import numpy as np
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from google.protobuf.message import Message
from ogapi.v1 import mapping_pb2 as pb

from ogmapping.frames.camera import Intrinsics
from ogmapping.persist.export import ColoredPoints
from ogmapping.queries import Rendered
from ogmapping.stats import MapStats, PoseSummary
from ogserver.access.tokens import TokenHash
from ogserver.api.validation import RenderSpec
from ogserver.errors import ServiceError
from ogserver.live.map_look import Splats
from ogserver.live.views import MappedFrame, Pending, Shown
from ogserver.recording.disk import StorageError
from ogserver.sessions.counters import FrameTotals, SessionCounters
from ogserver.sessions.hosting import Closed, Upload
from ogserver.sessions.stream_events import Acked, SessionClosed

DATACLASSES: dict[str, type] = {cls.__name__: cls for cls in (
    Intrinsics, Rendered, MapStats, PoseSummary, RenderSpec, SessionCounters, FrameTotals, Closed, Upload, Acked,
    SessionClosed, TokenHash, MappedFrame, Pending, Shown, Splats, ColoredPoints,
)}
# By full name: the service's messages, and the Foxglove image a mapped frame carries for the live views.
MESSAGES: dict[str, type[Message]] = {message.DESCRIPTOR.full_name: message for message in (
    *(getattr(pb, name) for name in pb.DESCRIPTOR.message_types_by_name), CompressedImage)}
ERRORS: dict[str, type[ServiceError]] = {cls.__name__: cls for cls in (ServiceError, StorageError)}
LENGTH = struct.Struct("!Q")
HEADER = struct.Struct("!II")


class RemoteFailure(Exception):
    """An unexpected failure in a worker, carried as its text (the servicer answers INTERNAL with it)."""


def dumps(value: Any) -> bytes:
    blobs: list[bytes] = []
    header = json.dumps(_encode(value, blobs)).encode()
    parts = [HEADER.pack(len(header), len(blobs)), header]
    for blob in blobs:
        parts += [LENGTH.pack(len(blob)), blob]
    return b"".join(parts)


def loads(data: bytes | memoryview) -> Any:
    view = memoryview(data)
    size, count = HEADER.unpack_from(view)
    at = HEADER.size + size
    header = json.loads(bytes(view[HEADER.size:at]))
    blobs = []
    for _ in range(count):
        (length,) = LENGTH.unpack_from(view, at)
        at += LENGTH.size
        blobs.append(view[at:at + length])
        at += length
    return _decode(header, blobs)


def _encode(value: Any, blobs: list[bytes]) -> Any:
    if value is None or isinstance(value, bool | int | float | str):
        return value
    if isinstance(value, list):
        return [_encode(item, blobs) for item in value]
    if isinstance(value, tuple):
        return {"t": [_encode(item, blobs) for item in value]}
    if isinstance(value, dict):
        return {"d": {str(key): _encode(item, blobs) for key, item in value.items()}}
    if isinstance(value, bytes | bytearray | memoryview):
        blobs.append(bytes(value))
        return {"b": len(blobs) - 1}
    if isinstance(value, np.ndarray):
        blobs.append(np.ascontiguousarray(value).tobytes())
        return {"a": len(blobs) - 1, "dtype": value.dtype.str, "shape": list(value.shape)}
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return {"p": str(value)}
    if isinstance(value, grpc.StatusCode):
        return {"s": value.name}
    if isinstance(value, Message):
        blobs.append(value.SerializeToString())
        return {"m": value.DESCRIPTOR.full_name, "b": len(blobs) - 1}
    if isinstance(value, ServiceError):
        return {"e": type(value).__name__ if type(value).__name__ in ERRORS else "ServiceError",
                "code": value.code.name, "message": value.message}
    if isinstance(value, BaseException):
        return {"x": str(value) or type(value).__name__}
    if dataclasses.is_dataclass(value) and type(value).__name__ in DATACLASSES:
        return {"c": type(value).__name__,
                "f": {item.name: _encode(getattr(value, item.name), blobs) for item in dataclasses.fields(value)}}
    raise TypeError(f"a worker message cannot carry a {type(value).__name__}")


def _decode(value: Any, blobs: list[memoryview]) -> Any:
    if isinstance(value, list):
        return [_decode(item, blobs) for item in value]
    if not isinstance(value, dict):
        return value
    if "t" in value:
        return tuple(_decode(item, blobs) for item in value["t"])
    if "d" in value:
        return {key: _decode(item, blobs) for key, item in value["d"].items()}
    if "a" in value:
        array = np.frombuffer(blobs[value["a"]], dtype=np.dtype(value["dtype"]))
        return array.reshape(value["shape"]).copy()
    if "m" in value:
        return MESSAGES[value["m"]].FromString(bytes(blobs[value["b"]]))
    if "b" in value:
        return bytes(blobs[value["b"]])
    if "p" in value:
        return Path(value["p"])
    if "s" in value:
        return grpc.StatusCode[value["s"]]
    if "e" in value:
        return ERRORS[value["e"]](grpc.StatusCode[value["code"]], value["message"])
    if "x" in value:
        return RemoteFailure(value["x"])
    return DATACLASSES[value["c"]](**{key: _decode(item, blobs) for key, item in value["f"].items()})


def send(sock: socket.socket, value: Any) -> None:
    """One message; the caller holds the socket's send lock."""
    data = dumps(value)
    sock.sendall(LENGTH.pack(len(data)) + data)


def receive(sock: socket.socket) -> Any:
    """The next message; EOFError once the other end has closed (or died)."""
    (length,) = LENGTH.unpack(_exactly(sock, LENGTH.size))
    return loads(_exactly(sock, length))


def _exactly(sock: socket.socket, size: int) -> bytearray:
    data = bytearray(size)
    view = memoryview(data)
    got = 0
    while got < size:
        read = sock.recv_into(view[got:])
        if not read:
            raise EOFError("the other end closed the connection")
        got += read
    return data
