"""Session tokens: issued when a session opens, checked on every call that names the session."""

from __future__ import annotations

import hashlib
import hmac
import secrets
from dataclasses import dataclass

import grpc

from ogserver.errors import ServiceError


def new_token() -> str:
    return secrets.token_urlsafe(32)


@dataclass(frozen=True)
class TokenHash:
    """What the server keeps of a session's token: a random salt and sha256(salt + token), so a
    checkpoint on disk (or a leaked one) never gives the token away. A token has 256 random bits:
    a fast hash is enough, nothing about it can be guessed."""

    salt: str  # hex
    sha256: str  # hex

    @classmethod
    def of(cls, token: str) -> TokenHash:
        salt = secrets.token_hex(16)
        return cls(salt, _digest(salt, token))

    def matches(self, presented: str) -> bool:
        """Constant-time comparison, so timing does not leak the digest."""
        return hmac.compare_digest(_digest(self.salt, presented), self.sha256)


def _digest(salt: str, token: str) -> str:
    return hashlib.sha256(bytes.fromhex(salt) + token.encode()).hexdigest()


def check_token(presented: str, expected: TokenHash) -> None:
    """Refuse a missing or wrong token."""
    if not presented:
        raise ServiceError(grpc.StatusCode.UNAUTHENTICATED, "x-session-token: metadata is missing")
    if not expected.matches(presented):
        raise ServiceError(grpc.StatusCode.UNAUTHENTICATED, "x-session-token: does not match the session")
