"""ListSessions lists the sessions there are: one that closed or expired while it was being listed (its worker
answers NOT_FOUND) is left out, and any other failure still reaches the caller."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import grpc
import pytest
from ogapi.v1 import mapping_pb2 as pb
from ogserver.api.servicer import infos
from ogserver.errors import ServiceError
from ogserver.sessions.counters import SessionCounters


@dataclass
class Listed:
    session_id: str
    failure: ServiceError | None = None
    streaming: bool = False
    recording: Path = Path("records/x.mcap")

    @property
    def config(self) -> pb.SessionConfig:
        return pb.SessionConfig(session_id=self.session_id, preset="sparse-fast")

    def counters(self) -> SessionCounters:
        if self.failure is not None:
            raise self.failure
        return SessionCounters(1, 0, 1, 0, 0, 40, 2.5, 1.0)


def test_a_session_gone_while_listed_is_left_out():
    gone = ServiceError(grpc.StatusCode.NOT_FOUND, "session_id: no session b")
    listed = infos([Listed("a"), Listed("b", gone), Listed("c")])
    assert [item.session_id for item in listed] == ["a", "c"] and listed[0].recording == "x.mcap"


def test_any_other_failure_reaches_the_caller():
    with pytest.raises(ServiceError, match="worker down"):
        infos([Listed("a", ServiceError(grpc.StatusCode.UNAVAILABLE, "worker down"))])
