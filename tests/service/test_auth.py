"""Session tokens: a missing or wrong one is refused with UNAUTHENTICATED, naming the metadata key."""

from __future__ import annotations

import grpc
import pytest
from ogserver import auth
from ogserver.errors import ServiceError


@pytest.mark.parametrize(("presented", "message"), [
    ("", "x-session-token: metadata is missing"),
    ("wrong", "x-session-token: does not match the session"),
])
def test_refusals(presented: str, message: str) -> None:
    with pytest.raises(ServiceError) as refusal:
        auth.check_token(presented, auth.new_token())
    assert refusal.value.code == grpc.StatusCode.UNAUTHENTICATED and refusal.value.message == message


def test_the_issued_token_is_accepted_and_unique() -> None:
    token = auth.new_token()
    auth.check_token(token, token)
    assert len(token) == 43 and token != auth.new_token()  # docs/service.md: 43 characters
