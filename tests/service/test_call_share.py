"""One caller holds at most its share of the server's call slots: a tenant that opened 40 unread
GetSnapshot calls once took all 32 slots, and every other tenant's calls were refused."""

from __future__ import annotations

from contextlib import ExitStack

import grpc
import pytest
from ogapi import API_KEY_METADATA_KEY
from ogserver.access.call_gate import CallGate, _Recorded, caller_of


class Refused(Exception):
    pass


class Context:
    """A servicer context of a caller with an API key, or only an address."""

    def __init__(self, key: str | None = None, peer: str = "ipv4:10.0.0.7:51000") -> None:
        self.key, self._peer = key, peer

    def invocation_metadata(self):
        return ((API_KEY_METADATA_KEY, self.key),) if self.key else ()

    def auth_context(self) -> dict:
        return {}

    def peer(self) -> str:
        return self._peer

    def abort(self, code: grpc.StatusCode, details: str = "") -> None:
        raise Refused(code, details)


def admitted(gate: CallGate, stack: ExitStack, context: Context) -> None:
    stack.enter_context(gate._admitted("/ogapi.v1.Mapping/GetSnapshot", _Recorded(context)))


def test_a_caller_holds_at_most_its_share_and_the_others_keep_theirs() -> None:
    gate = CallGate(4, lambda method, code: None, 1.0, None, per_caller=2)
    with ExitStack() as tenant, ExitStack() as other:
        for _ in range(2):
            admitted(gate, tenant, Context("tenant key"))
        with pytest.raises(Refused) as refusal:
            admitted(gate, tenant, Context("tenant key", peer="ipv4:10.0.0.8:1"))  # another connection, same key
        assert refusal.value.args[0] == grpc.StatusCode.RESOURCE_EXHAUSTED
        assert "max_calls_per_caller" in refusal.value.args[1]
        admitted(gate, other, Context("other key"))
        admitted(gate, other, Context())  # an address of its own
        with pytest.raises(Refused, match="limit of 4 concurrent calls"):
            admitted(gate, other, Context(peer="ipv6:[::1]:9"))
    admitted(gate, ExitStack(), Context("tenant key"))  # its calls ended: its share is free again


def test_callers_are_told_apart_by_key_then_address() -> None:
    assert caller_of(Context("k", "ipv4:1.2.3.4:5")) == caller_of(Context("k", "ipv4:9.9.9.9:1"))
    assert caller_of(Context(None, "ipv4:1.2.3.4:5")) == caller_of(Context(None, "ipv4:1.2.3.4:6"))
    assert caller_of(Context(None, "ipv4:1.2.3.4:5")) != caller_of(Context(None, "ipv4:1.2.3.5:5"))
    assert "secret" not in caller_of(Context("secret")), "a key is kept hashed"
