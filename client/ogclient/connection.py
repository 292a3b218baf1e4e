"""Reaching a server and naming a session: channel set-up, credentials files, call metadata."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import grpc
from ogapi import SESSION_METADATA_KEY, TOKEN_METADATA_KEY
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


def connect(address: str, timeout: float = 10.0) -> tuple[grpc.Channel, pb_grpc.MappingStub]:
    """An open channel, or ClientError when nothing answers at ``address`` within ``timeout``."""
    options = [
        ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
        ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
    ]
    channel = grpc.insecure_channel(address, options=options)
    try:
        grpc.channel_ready_future(channel).result(timeout=timeout)
    except grpc.FutureTimeoutError:
        channel.close()
        raise ClientError(f"cannot reach an ogserver at {address} (no connection within {timeout:g} s)") from None
    return channel, pb_grpc.MappingStub(channel)
