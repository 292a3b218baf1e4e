"""Cluster mode's parts that need no Ray: refusals crossing a process boundary, the cluster-wide
directory's limits, and the settings cluster mode refuses."""

from __future__ import annotations

import pickle

import grpc
import pytest
from ogserver.cluster.directory import Directory
from ogserver.errors import ServiceError
from ogserver.settings import Settings
from ogserver.storage import StorageError


@pytest.mark.parametrize("kind", [ServiceError, StorageError])
def test_refusals_keep_their_kind_code_and_message_across_processes(kind: type[ServiceError]) -> None:
    # Ray carries an actor's exception to the caller by pickling it (server-made, never client data).
    again = pickle.loads(pickle.dumps(kind(grpc.StatusCode.RESOURCE_EXHAUSTED, "data: too large")))
    assert type(again) is kind and again.code == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert again.message == "data: too large"


def refused(directory: Directory, owner: str, limit: int, quota: int) -> str:
    with pytest.raises(ServiceError) as refusal:
        directory.reserve(owner, limit, quota)
    assert refusal.value.code == grpc.StatusCode.RESOURCE_EXHAUSTED
    return refusal.value.message


def test_the_directory_holds_limits_across_the_cluster() -> None:
    directory = Directory()
    directory.reserve("alice", 3, 2)
    directory.commit("alice", "a1")
    directory.reserve("alice", 3, 2)  # being started: counted before it exists
    assert "alice already holds its limit of 2" in refused(directory, "alice", 3, 2)
    directory.release("alice")  # its actor failed to start
    directory.reserve("alice", 3, 2)
    directory.commit("alice", "a2")
    directory.reserve("bob", 3, 0)
    directory.commit("bob", "b1")
    assert "cluster already holds its limit of 3" in refused(directory, "carol", 3, 0)
    assert sorted(directory.sessions(None)) == ["a1", "a2", "b1"] and directory.sessions("bob") == ["b1"]
    directory.drop("a1")
    directory.reserve("carol", 3, 0)


def test_cluster_mode_refuses_what_it_cannot_do_yet() -> None:
    settings = Settings(cluster="auto")
    settings.live.foxglove_port = 0
    with pytest.raises(ValueError, match="not available in cluster mode"):
        settings.validate()
    with pytest.raises(ValueError, match="session_gpus"):
        Settings(cluster="auto", session_gpus=-0.5).validate()
    Settings(cluster="auto", session_gpus=0.25).validate()
