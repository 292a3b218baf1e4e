"""How the ports are opened: TLS (or mutual TLS) credentials, and HTTP/2 keepalive.

Keepalive pings let the server notice a client that vanished without closing its connection, so
its frame stream ends and releases the session's stream slot. The viewers' ports (the web view, the
Foxglove port) take the gRPC port's TLS, and its client CA, as an ``ssl.SSLContext``.
"""

from __future__ import annotations

import ssl
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


def tls_context(access: Access, setting: str) -> ssl.SSLContext | None:
    """The gRPC port's TLS for the viewer port ``setting`` (named in errors): its certificate, and its client
    CA (mutual TLS) when it has one."""
    if not access.tls_cert:
        return None
    tls = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    try:
        tls.load_cert_chain(access.tls_cert, access.tls_key)
        if access.tls_client_ca:
            tls.load_verify_locations(access.tls_client_ca)
            tls.verify_mode = ssl.CERT_REQUIRED
    except (OSError, ssl.SSLError) as error:
        raise ValueError(f"{setting}: cannot load the access.tls_* files: {error}") from None
    return tls


def certificate_names(certificate: dict | None) -> list[bytes]:
    """A verified client certificate's names as gRPC reports them: its DNS/URI names, else its common name."""
    if not certificate:
        return []
    alternatives = [value for kind, value in certificate.get("subjectAltName", ()) if kind in ("DNS", "URI")]
    if alternatives:
        return [name.encode() for name in alternatives]
    return [value.encode() for rdn in certificate.get("subject", ()) for key, value in rdn if key == "commonName"]
