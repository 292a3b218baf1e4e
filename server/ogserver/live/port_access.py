"""What the Foxglove port asks of a client, from the settings: the gRPC port's TLS, and a secret
whenever the gRPC port has API keys or TLS, so the live view is never more open than the API."""

from __future__ import annotations

import re
import secrets
import ssl
from dataclasses import dataclass
from pathlib import Path

from ogserver.live.front import Gate
from ogserver.settings import Settings

TOKEN = re.compile(r"[A-Za-z0-9._~-]{16,256}")  # long enough to guess in vain, and safe in a URL as it is


@dataclass(frozen=True)
class PortAccess:
    gate: Gate
    tls: ssl.SSLContext | None
    token_generated: bool  # a random per-server token, which the start-up log names in the URL

    def url(self, host: str, port: int) -> str:
        query = f"/?token={self.gate.token}" if self.gate.token else ""
        return f"{'wss' if self.tls else 'ws'}://{host}:{port}{query}"


def port_access(settings: Settings) -> PortAccess:
    access, live = settings.access, settings.live
    token, generated = "", False
    if live.foxglove_token_file:
        token = _read_token(Path(live.foxglove_token_file))
    elif access.tls_cert or not access.open:
        token, generated = secrets.token_urlsafe(24), True
    tls = None
    if access.tls_cert:
        tls = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        try:
            tls.load_cert_chain(access.tls_cert, access.tls_key)
        except (OSError, ssl.SSLError) as error:
            raise ValueError(f"live.foxglove_port: cannot load access.tls_cert and access.tls_key: {error}") \
                from None
    return PortAccess(Gate(frozenset(live.foxglove_origins), token), tls, generated)


def _read_token(path: Path) -> str:
    try:
        token = path.read_text().strip()
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(f"live.foxglove_token_file: cannot read {path}: {error}") from None
    if not TOKEN.fullmatch(token):
        raise ValueError(f"live.foxglove_token_file: {path} must hold one token of 16 to 256 letters, digits "
                         f"or . _ ~ - (python -c 'import secrets; print(secrets.token_urlsafe())' makes one)")
    return token
