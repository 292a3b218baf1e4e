"""Who sees which sessions on the viewers (the web view, the Foxglove port): the gRPC port's rules.

A viewer presents an API key (``key``), a session token (``token``), a client certificate (mutual
TLS), or nothing on an open server. A key or a certificate names a caller, who sees the sessions it
created or restored, as ListSessions shows them; a session token shows that one session, as every
gRPC call that names a session allows; an open server's anonymous caller sees every session. Wrong
credentials count against the address like the gRPC port's (``FailedAuthentications``), in one count
for both viewers.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from urllib.parse import urlencode

import grpc

from ogserver.access.callers import Callers
from ogserver.access.failed_auth import FailedAuthentications
from ogserver.errors import ServiceError
from ogserver.sessions.hosting import ViewedHost, ViewedSession


@dataclass(frozen=True)
class Credential:
    key: str = ""
    token: str = ""
    certificate_names: list[bytes] = field(default_factory=list)
    address: str = ""  # the client's, for counting failures

    @property
    def presented(self) -> bool:
        return bool(self.key or self.token or self.certificate_names)

    def query(self) -> str:
        """The credential as a page's links carry it ("" for none, else "?key=..." or "?token=...")."""
        pairs = {"key": self.key} if self.key else {"token": self.token} if self.token else {}
        return f"?{urlencode(pairs)}" if pairs else ""


@dataclass(frozen=True)
class Scope:
    """What one credential sees: the sessions ``owner`` owns, or the one session ``session_id``, or (both
    None) every session. Asked each time, so it follows sessions opened and closed since."""

    owner: str | None = None
    session_id: str | None = None

    def sessions(self, registry: ViewedHost) -> list[ViewedSession]:
        if self.session_id is not None:
            return [session for session in registry.sessions() if session.id == self.session_id]
        return registry.sessions(self.owner)

    def sees(self, registry: ViewedHost, session_id: str | None) -> bool:
        """Whether the session is one this scope shows (None, a topic of no session: only to everything)."""
        if session_id is None:
            return self.owner is None and self.session_id is None
        return any(session.id == session_id for session in self.sessions(registry))


EVERYTHING = Scope()


class Viewers:
    """The checks both viewers make of a credential, against the gRPC port's callers and the registry."""

    def __init__(self, registry: ViewedHost, callers: Callers, failures: FailedAuthentications) -> None:
        self.registry = registry
        self.callers = callers
        self.failures = failures

    def scope(self, credential: Credential) -> Scope:
        """What ``credential`` sees; ServiceError UNAUTHENTICATED for a wrong or missing one (counted,
        RESOURCE_EXHAUSTED past the limits)."""
        with self.failures.guard(credential.address):
            if credential.token:
                return self._held(credential.token)
            try:
                return Scope(owner=self.callers.identify(credential.key, credential.certificate_names or None))
            except ServiceError:
                if not credential.key:
                    raise
                return self._held(credential.key)  # a session token, typed into the page's one field

    def _held(self, token: str) -> Scope:
        """The session whose token this is."""
        held = [session for session in self.registry.sessions() if session.token.matches(token)]
        if not held:
            raise ServiceError(grpc.StatusCode.UNAUTHENTICATED, "not an API key or session token this server accepts")
        return Scope(session_id=held[0].id)
