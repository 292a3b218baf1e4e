"""TLS channel credentials from PEM files, for ogclient and the server's container health check."""

from __future__ import annotations

from pathlib import Path

import grpc


def channel_credentials(ca: str = "", cert: str = "", key: str = "") -> grpc.ChannelCredentials:
    """Trust ``ca`` (the system's CAs when empty); present ``cert``/``key`` to a server that asks for one."""
    if bool(cert) != bool(key):
        raise ValueError("--tls-cert and --tls-key go together")
    try:
        root, chain, private = (Path(path).read_bytes() if path else None for path in (ca, cert, key))
    except OSError as error:
        raise ValueError(f"cannot read {error.filename}: {error.strerror}") from None
    return grpc.ssl_channel_credentials(root_certificates=root, private_key=private, certificate_chain=chain)
