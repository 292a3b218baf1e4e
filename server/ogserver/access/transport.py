"""How the port is opened: TLS (or mutual TLS) credentials, and HTTP/2 keepalive.

Keepalive pings let the server notice a client that vanished without closing its connection, so
its frame stream ends and releases the session's stream slot.
"""

from __future__ import annotations

from pathlib import Path

import grpc

from ogserver.settings import Access


def _read(path: str, setting: str) -> bytes:
    try:
        return Path(path).read_bytes()
    except OSError as error:
        raise ValueError(f"access.{setting}: cannot read {path}: {error.strerror}") from None


def server_credentials(access: Access) -> grpc.ServerCredentials | None:
    """TLS credentials when a certificate is set; with a client CA, clients must present a certificate."""
    if not access.tls_cert:
        return None
    pair = (_read(access.tls_key, "tls_key"), _read(access.tls_cert, "tls_cert"))
    client_ca = _read(access.tls_client_ca, "tls_client_ca") if access.tls_client_ca else None
    return grpc.ssl_server_credentials([pair], root_certificates=client_ca, require_client_auth=client_ca is not None)


def keepalive_options(access: Access) -> list[tuple[str, int]]:
    if not access.keepalive_seconds:
        return []
    return [
        ("grpc.keepalive_time_ms", round(access.keepalive_seconds * 1000)),
        ("grpc.keepalive_timeout_ms", round(access.keepalive_timeout_seconds * 1000)),
        ("grpc.http2.max_pings_without_data", 0),  # ping a client that has stopped sending, too
    ]
