"""Session tokens: a missing or wrong one is refused with UNAUTHENTICATED, naming the metadata key."""

from __future__ import annotations

import grpc
import pytest
from ogserver.access import tokens
from ogserver.errors import ServiceError


@pytest.mark.parametrize(("presented", "message"), [
    ("", "x-session-token: metadata is missing"),
    ("wrong", "x-session-token: does not match the session"),
])
def test_refusals(presented: str, message: str) -> None:
    with pytest.raises(ServiceError) as refusal:
        tokens.check_token(presented, tokens.TokenHash.of(tokens.new_token()))
    assert refusal.value.code == grpc.StatusCode.UNAUTHENTICATED and refusal.value.message == message


def test_the_issued_token_is_accepted_and_unique() -> None:
    token = tokens.new_token()
    tokens.check_token(token, tokens.TokenHash.of(token))
    assert len(token) == 43 and token != tokens.new_token()  # docs/service.md: 43 characters


def test_the_server_keeps_a_salted_hash_not_the_token() -> None:
    token = tokens.new_token()
    first, second = tokens.TokenHash.of(token), tokens.TokenHash.of(token)
    assert first.salt != second.salt and first.sha256 != second.sha256  # salted: equal tokens hash apart
    assert token not in (first.salt, first.sha256) and first.matches(token) and second.matches(token)
    assert not first.matches(token[:-1])
