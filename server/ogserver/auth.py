"""Session tokens: issued when a session opens, checked on every call that names the session."""

from __future__ import annotations

import hmac
import secrets

import grpc

from ogserver.errors import ServiceError


def new_token() -> str:
    return secrets.token_urlsafe(32)


def check_token(presented: str, expected: str) -> None:
    """Refuse a missing or wrong token; compare in constant time so timing does not leak the token."""
    if not presented:
        raise ServiceError(grpc.StatusCode.UNAUTHENTICATED, "x-session-token: metadata is missing")
    if not hmac.compare_digest(presented.encode(), expected.encode()):
        raise ServiceError(grpc.StatusCode.UNAUTHENTICATED, "x-session-token: does not match the session")
