"""Reaching a server and naming a session: channel set-up (TLS, API key), credentials files, call metadata."""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import grpc
from ogapi import API_KEY_METADATA_KEY, SESSION_METADATA_KEY, TOKEN_METADATA_KEY
from ogapi.tls import channel_credentials
from ogapi.v1 import mapping_pb2 as pb
from ogapi.v1 import mapping_pb2_grpc as pb_grpc

DEFAULT_SERVER = os.environ.get("OGMAP_SERVER", "127.0.0.1:50051")
MAX_MESSAGE_BYTES = 256 << 20


class ClientError(Exception):
    """A failure worth one line to the user (the CLI prints it and exits non-zero)."""


def describe(error: grpc.RpcError) -> str:
    code = error.code() if hasattr(error, "code") else None
    details = error.details() if hasattr(error, "details") else str(error)
    return f"{code.name if code else 'ERROR'}: {details}"


@dataclass(frozen=True)
class SessionRef:
    """What identifies and authorises calls on one session."""

    session_id: str
    token: str

    def metadata(self) -> tuple[tuple[str, str], ...]:
        return ((TOKEN_METADATA_KEY, self.token),)

    def stream_metadata(self) -> tuple[tuple[str, str], ...]:
        return ((SESSION_METADATA_KEY, self.session_id), (TOKEN_METADATA_KEY, self.token))

    @classmethod
    def from_credentials(cls, credentials: pb.SessionCredentials) -> SessionRef:
        return cls(credentials.session_id, credentials.token)

    def save(self, path: str | Path, server: str) -> None:
        """A small JSON file later commands accept as ``--session``; it holds a secret, so mode 600."""
        target = Path(path)
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(json.dumps({"server": server, "session_id": self.session_id, "token": self.token}) + "\n")
        target.chmod(0o600)

    @classmethod
    def load(cls, path: str | Path) -> SessionRef:
        try:
            data = json.loads(Path(path).read_text())
            return cls(str(data["session_id"]), str(data["token"]))
        except (OSError, ValueError, KeyError, TypeError) as error:
            raise ClientError(f"cannot read session file {path}: {error}") from None


@dataclass(frozen=True)
class Transport:
    """How to reach the server: TLS (the CA to trust, a client certificate for mutual TLS) and an API key."""

    tls: bool = False  # TLS with the system's trusted CAs, unless ``ca`` names one
    ca: str = ""
    cert: str = ""
    key: str = ""
    api_key: str = ""  # sent as metadata x-api-key on every call

    @property
    def secure(self) -> bool:
        return self.tls or bool(self.ca or self.cert or self.key)

    def credentials(self) -> grpc.ChannelCredentials:
        return channel_credentials(self.ca, self.cert, self.key)


class _ApiKey(grpc.UnaryUnaryClientInterceptor, grpc.UnaryStreamClientInterceptor,
              grpc.StreamUnaryClientInterceptor, grpc.StreamStreamClientInterceptor):
    def __init__(self, key: str) -> None:
        self._key = key

    def intercept_unary_unary(self, continuation: Callable[..., Any], details: Any, request: Any) -> Any:
        metadata = [*(details.metadata or ()), (API_KEY_METADATA_KEY, self._key)]
        return continuation(details._replace(metadata=metadata), request)

    intercept_unary_stream = intercept_stream_unary = intercept_stream_stream = intercept_unary_unary


def connect(
    address: str, timeout: float = 10.0, transport: Transport = Transport()
) -> tuple[grpc.Channel, pb_grpc.MappingStub]:
    """An open channel, or ClientError when nothing answers at ``address`` within ``timeout``."""
    options = [
        ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
        ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
    ]
    if transport.secure:
        channel = grpc.secure_channel(address, transport.credentials(), options=options)
    else:
        channel = grpc.insecure_channel(address, options=options)
    try:
        grpc.channel_ready_future(channel).result(timeout=timeout)
    except grpc.FutureTimeoutError:
        channel.close()
        hint = " (over TLS: check --tls-ca and the server's certificate and name)" if transport.secure else ""
        raise ClientError(f"cannot reach an ogserver at {address} (no connection within {timeout:g} s){hint}") from None
    if transport.api_key:
        channel = grpc.intercept_channel(channel, _ApiKey(transport.api_key))
    return channel, pb_grpc.MappingStub(channel)
