"""Who is calling: an API key's name, a client certificate's name, or the anonymous caller of an open server.

The identity owns the sessions it creates or restores: it counts against ``max_sessions_per_client``
and ListSessions shows a caller only its own sessions. Calls on one session are authorised by the
session's token instead, so a token can be handed to another client.
"""

from __future__ import annotations

from collections.abc import Sequence

import grpc
from ogapi import API_KEY_METADATA_KEY

from ogserver import apikeys
from ogserver.errors import ServiceError
from ogserver.settings import Access

ANONYMOUS = "anonymous"


class Callers:
    def __init__(self, access: Access) -> None:
        self._names = apikeys.load(access)  # digest -> name
        self._certificates = bool(access.tls_client_ca)

    @property
    def open(self) -> bool:
        """No API keys and no client certificates: anyone who reaches the port may create sessions."""
        return not self._names and not self._certificates

    def describe(self) -> str:
        """What a caller must present, for the start-up log."""
        ways = [f"an API key ({len(self._names)} configured)"] if self._names else []
        if self._certificates:
            ways.append("a client certificate")
        return " or ".join(ways)

    def identify(self, api_key: str, certificate_names: Sequence[bytes] | None) -> str:
        """The caller's identity: a presented key must be known; without one, the verified certificate's name."""
        if api_key and self._names:
            name = self._names.get(apikeys.digest(api_key))
            if name is None:
                raise ServiceError(grpc.StatusCode.UNAUTHENTICATED,
                                   f"{API_KEY_METADATA_KEY}: not a key this server accepts")
            return f"key:{name}"
        if self._certificates and certificate_names:
            return f"cert:{certificate_names[0].decode(errors='replace')}"
        if self._names:
            raise ServiceError(grpc.StatusCode.UNAUTHENTICATED, f"{API_KEY_METADATA_KEY}: metadata is missing")
        return ANONYMOUS
