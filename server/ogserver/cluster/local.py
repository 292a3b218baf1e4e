"""A real Ray cluster on this machine, for tests, benchmarks and trying cluster mode out.

Each node is a ``ray start --block`` process (the head first, then nodes that join it) on 127.0.0.1,
in a process group of its own, so stopping it ends exactly the processes that node started and
nothing else of the machine's (never ``ray stop``, which stops every Ray process it finds). The raylet
starts its workers (the session actors) in process groups of their own, so losing a node is SIGKILL
to the node's group and to every process descended from it, found by their parent ids in /proc. Each
node's raylet listens on a port chosen here, which is how a node of ``ray.nodes()`` is told apart from
the others on one IP. The nodes inherit this process's environment: its PYTHONPATH is how their workers import ogserver.
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path

RAY = Path(sys.executable).parent / "ray"
STOP_SECONDS = 5.0
START_SECONDS = 90.0
STARTED = "Ray runtime started"  # what ``ray start`` logs once its node has joined
# How soon the head declares a lost node dead (Ray's defaults take about 30 s): 1 s checks, 3 misses.
FAST_FAILURE_DETECTION = {"RAY_health_check_period_ms": "1000", "RAY_health_check_timeout_ms": "1000",
                          "RAY_health_check_failure_threshold": "3", "RAY_health_check_initial_delay_ms": "1000"}


def descendants(root: int) -> list[int]:
    """The ids of every process below ``root`` (Linux /proc), whatever their process group."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with suppress(OSError, ValueError, IndexError):
            fields = stat.read_text().rsplit(")", 1)[1].split()  # after "pid (comm)": state, ppid, ...
            children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    found, pending = [], [root]
    while pending:
        below = children.get(pending.pop(), [])
        found.extend(below)
        pending.extend(below)
    return found


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@dataclass
class Node:
    process: subprocess.Popen
    manager_port: int  # its raylet's port: ``NodeManagerPort`` in ``ray.nodes()``

    def stop(self) -> None:
        """SIGTERM to the node's process group (``ray start --block`` ends the node), then SIGKILL to what is left."""
        if self.process.poll() is None:
            os.killpg(self.process.pid, signal.SIGTERM)
            try:
                self.process.wait(STOP_SECONDS)
            except subprocess.TimeoutExpired:
                os.killpg(self.process.pid, signal.SIGKILL)
                self.process.wait()
        self._kill_group()  # workers the node started and left behind

    def kill(self) -> None:
        """The node is lost at once: its raylet, object store and workers get SIGKILL together."""
        self._kill_group()
        self.process.wait()

    def _kill_group(self) -> None:
        below = descendants(self.process.pid)
        with suppress(ProcessLookupError):
            os.killpg(self.process.pid, signal.SIGKILL)
        for pid in below:
            with suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)


@dataclass
class LocalCluster:
    address: str
    nodes: list[Node]  # the head first
    temp_dir: Path  # Ray's, for every node of this machine: session_latest/logs holds the workers' logs

    def worker_logs(self) -> str:
        """What the cluster's workers (the session actors among them) have written to stderr so far."""
        return "".join(path.read_text(errors="replace")
                       for path in sorted((self.temp_dir / "session_latest" / "logs").glob("worker-*.err")))

    def node_of(self, node_id: str) -> Node:
        """The node whose Ray node id is ``node_id`` (as ``ray.get_runtime_context().get_node_id()`` says)."""
        import ray

        ports = {entry["NodeID"]: entry["NodeManagerPort"] for entry in ray.nodes()}
        return next(node for node in self.nodes if node.manager_port == ports[node_id])


def wait_started(process: subprocess.Popen, log: Path) -> None:
    deadline = time.monotonic() + START_SECONDS
    while STARTED not in log.read_text(errors="replace"):
        if process.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"a Ray node did not start (see {log})")
        time.sleep(0.2)


@contextmanager
def local_cluster(logs: Path, workers: int = 1, cpus_per_node: int = 1, head_cpus: int | None = None,
                  fast_failure_detection: bool = False) -> Iterator[LocalCluster]:
    """A head and ``workers`` nodes that join it, while they run; logs under ``logs``. ``head_cpus`` (default
    ``cpus_per_node``) 0 keeps sessions off the head, so losing a worker node never takes the cluster's GCS."""
    temp_dir = tempfile.mkdtemp(prefix="ogray-")  # Ray's socket paths must stay short: not under a deep tmp path
    address = f"127.0.0.1:{free_port()}"
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0", **(FAST_FAILURE_DETECTION if fast_failure_detection else {})}
    common = ["--block", "--node-ip-address=127.0.0.1", "--num-gpus=0", "--disable-usage-stats"]
    head = ["--head", f"--port={address.rsplit(':', 1)[1]}", "--include-dashboard=false", f"--temp-dir={temp_dir}",
            f"--num-cpus={cpus_per_node if head_cpus is None else head_cpus}"]
    started: list[Node] = []
    try:
        for number in range(workers + 1):
            joining = head if number == 0 else [f"--address={address}", f"--num-cpus={cpus_per_node}"]
            port = free_port()
            with open(logs / f"node{number}.log", "w") as log:
                process = subprocess.Popen([str(RAY), "start", *joining, *common, f"--node-manager-port={port}"],
                                           env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
            started.append(Node(process, port))
            wait_started(process, logs / f"node{number}.log")  # a node that joins a head still starting may hang
        yield LocalCluster(address, started, Path(temp_dir))
    finally:
        for node in reversed(started):
            node.stop()
        shutil.rmtree(temp_dir, ignore_errors=True)
