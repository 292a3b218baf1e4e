"""What the Foxglove port asks of a client, from the settings: the gRPC port's TLS (and client CA), the
origins allowed, and the operator's see-everything token when ``--foxglove-token-file`` sets one. Who
sees which session is the web view's rule (``access/viewers.py``), given by the ``Viewers`` passed in."""

from __future__ import annotations

import re
import ssl
from dataclasses import dataclass
from pathlib import Path

from ogserver.access.transport import tls_context
from ogserver.access.viewers import Viewers
from ogserver.live.front import Gate
from ogserver.settings import Settings

TOKEN = re.compile(r"[A-Za-z0-9._~-]{16,256}")  # long enough to guess in vain, and safe in a URL as it is


@dataclass(frozen=True)
class PortAccess:
    origins: frozenset[str]
    token: str  # the operator's, which sees every session ("" = none)
    tls: ssl.SSLContext | None

    def gate(self, viewers: Viewers) -> Gate:
        return Gate(viewers, self.origins, self.token)

    def url(self, host: str, port: int) -> str:
        return f"{'wss' if self.tls else 'ws'}://{host}:{port}"


def port_access(settings: Settings) -> PortAccess:
    live = settings.live
    token = _read_token(Path(live.foxglove_token_file)) if live.foxglove_token_file else ""
    return PortAccess(frozenset(live.foxglove_origins), token, tls_context(settings.access, "live.foxglove_port"))


def _read_token(path: Path) -> str:
    try:
        token = path.read_text().strip()
    except (OSError, UnicodeDecodeError) as error:
        raise ValueError(f"live.foxglove_token_file: cannot read {path}: {error}") from None
    if not TOKEN.fullmatch(token):
        raise ValueError(f"live.foxglove_token_file: {path} must hold one token of 16 to 256 letters, digits "
                         f"or . _ ~ - (python -c 'import secrets; print(secrets.token_urlsafe())' makes one)")
    return token
