"""Cluster mode's parts that need no Ray: refusals crossing a process boundary, the cluster-wide
directory's limits, and the settings cluster mode refuses."""

from __future__ import annotations

import pickle

import grpc
import pytest
from ogserver.cluster.directory import Directory
from ogserver.errors import ServiceError
from ogserver.recording.disk import StorageError
from ogserver.settings import Settings


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
    directory = Directory(lambda session_id: True)
    directory.reserve("alice", 3, 2)
    directory.commit("alice", "a1")
    directory.reserve("alice", 3, 2)  # being started: counted before it exists
    assert "alice already holds its limit of 2" in refused(directory, "alice", 3, 2)
    directory.release("alice", "a0")  # its actor failed to start
    directory.reserve("alice", 3, 2)
    directory.commit("alice", "a2")
    directory.reserve("bob", 3, 0)
    directory.commit("bob", "b1")
    assert "cluster already holds its limit of 3" in refused(directory, "carol", 3, 0)
    assert sorted(directory.sessions(None)) == ["a1", "a2", "b1"] and directory.sessions("bob") == ["b1"]
    directory.drop("a1")
    directory.reserve("carol", 3, 0)


def test_a_session_dead_for_good_gives_its_place_back_when_the_cluster_is_full() -> None:
    dead: set[str] = set()
    directory = Directory(lambda session_id: session_id not in dead)
    for session_id in ("a1", "a2"):
        directory.reserve("alice", 2, 0)
        directory.commit("alice", session_id)
    assert "cluster already holds its limit of 2" in refused(directory, "bob", 2, 0)  # both alive
    dead.add("a1")  # its actor's restarts are spent
    directory.reserve("bob", 2, 0)
    directory.commit("bob", "b1")
    assert sorted(directory.sessions(None)) == ["a2", "b1"]
    assert "cluster already holds its limit of 2" in refused(directory, "carol", 2, 0)


def test_a_new_session_goes_to_the_node_holding_the_fewest() -> None:
    directory = Directory(lambda session_id: True)
    assert directory.place("s1", ["n1", "n2"]) == "n1"
    assert directory.place("s2", ["n1", "n2"]) == "n2"  # s1 is held for n1 before its actor runs
    directory.placed("s1", "n2")  # its soft affinity was not kept (n1 full), or it restarted on n2
    assert directory.place("s3", ["n1", "n2"]) == "n1"
    directory.drop("s2")
    directory.release("alice", "s3")
    assert directory.place("s4", ["n1", "n2", "n3"]) == "n1"
    assert directory.place("s5", ["n2", "n3"]) == "n3"  # n1 cannot take it


def test_cluster_mode_refuses_what_it_cannot_do_yet() -> None:
    settings = Settings(cluster="auto")
    settings.live.foxglove_port = 0
    with pytest.raises(ValueError, match="not available in cluster mode"):
        settings.validate()
    with pytest.raises(ValueError, match="session_gpus"):
        Settings(cluster="auto", session_gpus=-0.5).validate()
    Settings(cluster="auto", session_gpus=0.25).validate()
    with pytest.raises(ValueError, match="without cluster"):
        Settings(shared_storage="s3://bucket/recordings").validate()
    with pytest.raises(ValueError, match="fsspec URL"):
        Settings(cluster="auto", shared_storage="/mnt/shared").validate()  # a path: that is record_dir's job
    Settings(cluster="auto", shared_storage="s3://bucket/recordings").validate()
