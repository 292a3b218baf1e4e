"""A real local Ray cluster for the cluster-mode tests: a head node and a second node, each a
``ray start --block`` process of its own (its own process group, stopped by that group's id), on
127.0.0.1 with one CPU each, so two one-CPU sessions cannot share a node."""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path

import pytest

pytest.importorskip("ray", reason="cluster mode needs Ray: the 'cluster' extra (make cluster-test installs it)")

REPO = Path(__file__).resolve().parents[2]
RAY = Path(sys.executable).parent / "ray"


@dataclass
class RayCluster:
    address: str
    nodes: list[subprocess.Popen]
    logs: Path


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def stop(node: subprocess.Popen) -> None:
    """SIGTERM to the node's process group (ray start --block ends the node's processes), then SIGKILL."""
    if node.poll() is None:
        os.killpg(node.pid, signal.SIGTERM)
        try:
            node.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(node.pid, signal.SIGKILL)
            node.wait()
    with suppress(ProcessLookupError):
        os.killpg(node.pid, signal.SIGKILL)  # workers the node started and left behind


@contextmanager
def ray_cluster(logs: Path) -> Iterator[RayCluster]:
    """The two nodes started (the second joins the head on its own), stopped on exit; logs under ``logs``."""
    # Ray's socket paths must stay short: its temp dir goes under /tmp, not pytest's deep tmp path.
    temp_dir = tempfile.mkdtemp(prefix="ogray-")
    port = free_port()
    address = f"127.0.0.1:{port}"
    paths = [str(REPO), str(REPO / "proto"), str(REPO / "server"), str(REPO / "client")]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(paths), "RAY_USAGE_STATS_ENABLED": "0"}
    common = ["--block", "--node-ip-address=127.0.0.1", "--num-cpus=1", "--num-gpus=0", "--disable-usage-stats"]
    commands = [
        [str(RAY), "start", "--head", f"--port={port}", "--include-dashboard=false", f"--temp-dir={temp_dir}", *common],
        [str(RAY), "start", f"--address={address}", *common],
    ]
    nodes = []
    try:
        for number, command in enumerate(commands):
            with open(logs / f"node{number}.log", "w") as log:
                nodes.append(subprocess.Popen(command, env=env, stdout=log, stderr=subprocess.STDOUT,
                                              start_new_session=True))
        yield RayCluster(address, nodes, logs)
    finally:
        for node in reversed(nodes):
            stop(node)
        shutil.rmtree(temp_dir, ignore_errors=True)
