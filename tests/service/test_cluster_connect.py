"""Cluster mode's start against a Ray address nothing answers at: refused within a bounded time, in one
line naming the address. Ray is stood in for where it is not installed; with Ray, ``ogserver`` itself."""

from __future__ import annotations

import importlib
import socket
import subprocess
import sys
import time
import types
from collections.abc import Iterator
from pathlib import Path

import pytest
from ogserver.cluster.connect import endpoint, join
from ogserver.settings import Settings

RAY_MODULES = ("ray", "ray.actor", "ray.exceptions", "ray.util", "ray.util.scheduling_strategies")
CLUSTER_MODULES = ("ogserver.cluster.host", "ogserver.cluster.actor", "ogserver.cluster.remote")


class RayWouldRetry(Exception):
    """What the stand-in ``ray.init`` raises: the real one retries here for a minute or more."""


def closed_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.fixture
def fake_ray() -> Iterator[types.ModuleType]:
    """A stand-in for the Ray modules ``ogserver.cluster.host`` imports, whose ``init`` records its calls;
    the real modules (when installed) and the cluster modules are put back afterwards."""
    saved = {name: sys.modules.get(name) for name in RAY_MODULES + CLUSTER_MODULES}
    modules = {name: types.ModuleType(name) for name in RAY_MODULES}
    ray = modules["ray"]
    ray.ObjectRef = object
    ray.calls = []

    def init(**kwargs: object) -> None:
        ray.calls.append(kwargs)
        raise RayWouldRetry()

    ray.init = init
    modules["ray.actor"].ActorHandle = object
    for name in ("GetTimeoutError", "RayActorError", "RayTaskError"):
        setattr(modules["ray.exceptions"], name, type(name, (Exception,), {}))
    modules["ray.util.scheduling_strategies"].NodeAffinitySchedulingStrategy = object
    try:
        for name in CLUSTER_MODULES:
            sys.modules.pop(name, None)
        sys.modules.update(modules)
        yield ray
    finally:
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module


def test_an_unreachable_address_stops_the_start_before_ray_retries(fake_ray: types.ModuleType) -> None:
    host = importlib.import_module("ogserver.cluster.host")
    address = f"127.0.0.1:{closed_port()}"
    start = time.monotonic()
    with pytest.raises(RuntimeError) as refusal:
        host.ClusterHost(Settings(cluster=address))
    assert time.monotonic() - start < 5.0
    assert fake_ray.calls == []
    message = str(refusal.value)
    assert message.startswith(f"cannot reach the Ray cluster at {address} within 15 s") and "\n" not in message


def test_an_address_that_answers_is_handed_to_ray(fake_ray: types.ModuleType) -> None:
    host = importlib.import_module("ogserver.cluster.host")
    with socket.socket() as listening:
        listening.bind(("127.0.0.1", 0))
        listening.listen()
        address = f"ray://127.0.0.1:{listening.getsockname()[1]}"
        with pytest.raises(RuntimeError, match=f"^cannot join the Ray cluster at {address}: RayWouldRetry$"):
            host.ClusterHost(Settings(cluster=address))
    assert [call["address"] for call in fake_ray.calls] == [address]


def test_a_silent_address_is_given_up_after_the_configured_time() -> None:
    """A TEST-NET address (RFC 5737) nobody routes: dropped, refused or unreachable, never waited on longer."""
    start = time.monotonic()
    with pytest.raises(RuntimeError, match=r"^cannot reach the Ray cluster at 192\.0\.2\.1:6379 within 0\.5 s"):
        join("192.0.2.1:6379", 0.5, lambda: pytest.fail("connected"))
    assert time.monotonic() - start < 3.0


@pytest.mark.parametrize(("address", "found"), [
    ("10.0.0.5:6379", ("10.0.0.5", 6379)), ("ray://head:10001", ("head", 10001)), ("[::1]:6379", ("::1", 6379)),
    ("auto", None), ("ray://head", None),
])
def test_the_endpoint_of_a_ray_address(address: str, found: tuple[str, int] | None) -> None:
    assert endpoint(address) == found


def test_settings_refuse_a_negative_connect_time() -> None:
    with pytest.raises(ValueError, match="cluster_connect_seconds"):
        Settings(cluster="auto", cluster_connect_seconds=-1.0).validate()


@pytest.mark.cluster
def test_ogserver_with_an_unreachable_cluster_exits_in_one_line(tmp_path: Path) -> None:
    pytest.importorskip("ray", reason="cluster mode needs Ray: the 'cluster' extra (make cluster-test installs it)")
    address = f"127.0.0.1:{closed_port()}"
    start = time.monotonic()
    done = subprocess.run([sys.executable, "-m", "ogserver", "--cluster", address, "--address", "127.0.0.1:0",
                           "--record-dir", str(tmp_path), "--device", "cpu"], capture_output=True, text=True,
                          timeout=120)
    assert time.monotonic() - start < 60.0  # the interpreter, torch and Ray's import included
    assert done.returncode == 2
    assert done.stderr.strip().splitlines()[-1].startswith(f"ogserver: cannot reach the Ray cluster at {address}")
