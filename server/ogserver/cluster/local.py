"""A real Ray cluster on this machine, for tests, benchmarks and trying cluster mode out.

Each node is a ``ray start --block`` process (the head first, then nodes that join it) on 127.0.0.1,
in a process group of its own, so stopping it ends exactly the processes that node started and
nothing else of the machine's (never ``ray stop``, which stops every Ray process it finds). The
nodes inherit this process's environment: its PYTHONPATH is how their workers import ogserver.
"""

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
from pathlib import Path

RAY = Path(sys.executable).parent / "ray"
STOP_SECONDS = 5.0


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def stop(node: subprocess.Popen) -> None:
    """SIGTERM to the node's process group (``ray start --block`` ends the node), then SIGKILL to what is left."""
    if node.poll() is None:
        os.killpg(node.pid, signal.SIGTERM)
        try:
            node.wait(STOP_SECONDS)
        except subprocess.TimeoutExpired:
            os.killpg(node.pid, signal.SIGKILL)
            node.wait()
    with suppress(ProcessLookupError):
        os.killpg(node.pid, signal.SIGKILL)  # workers the node started and left behind


@contextmanager
def local_cluster(logs: Path, nodes: int = 2, cpus_per_node: int = 1) -> Iterator[str]:
    """The cluster's address while ``nodes`` nodes run (the others join the head on their own); logs under
    ``logs``."""
    temp_dir = tempfile.mkdtemp(prefix="ogray-")  # Ray's socket paths must stay short: not under a deep tmp path
    address = f"127.0.0.1:{free_port()}"
    env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0"}
    common = ["--block", "--node-ip-address=127.0.0.1", f"--num-cpus={cpus_per_node}", "--num-gpus=0",
              "--disable-usage-stats"]
    head = ["--head", f"--port={address.rsplit(':', 1)[1]}", "--include-dashboard=false", f"--temp-dir={temp_dir}"]
    started: list[subprocess.Popen] = []
    try:
        for number in range(nodes):
            joining = head if number == 0 else [f"--address={address}"]
            with open(logs / f"node{number}.log", "w") as log:
                started.append(subprocess.Popen([str(RAY), "start", *joining, *common], env=env, stdout=log,
                                                stderr=subprocess.STDOUT, start_new_session=True))
        yield address
    finally:
        for node in reversed(started):
            stop(node)
        shutil.rmtree(temp_dir, ignore_errors=True)
