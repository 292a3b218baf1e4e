"""docker/compose.yaml agrees with the server and the image: its command is flags ogserver accepts, every
port the server listens on is published (on the host's loopback), the health check asks the gRPC port,
the record dir is the volume, and the build names a stage of the Dockerfile. Each host port comes from an
environment variable (`${VAR:-default}`, the container's port by default) that the container test sets to
a free port. Where a compose provider with `config` is installed, it reads the file too."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
import yaml
from ogserver import settings
from ogserver.__main__ import parser

REPO = Path(__file__).resolve().parents[1]
COMPOSE = REPO / "docker" / "compose.yaml"
CONTAINER_TEST = REPO / "docker" / "container-test.sh"
# host:${VARIABLE:-default host port}:container port
PORT = re.compile(r"(?P<host>[^:]+):\$\{(?P<variable>OGMAP_[A-Z]+_PORT):-(?P<default>\d+)\}:(?P<container>\d+)")


def server() -> dict[str, Any]:
    return yaml.safe_load(COMPOSE.read_text())["services"]["server"]


def configured() -> settings.Settings:
    """The settings the compose command gives the server (refuses unknown flags and invalid values)."""
    flags = {key: value for key, value in vars(parser().parse_args(server()["command"])).items()
             if key not in ("config", "log_level")}
    loaded = settings.load(None, flags)
    loaded.validate()
    return loaded


def published() -> dict[int, tuple[str, int]]:
    """Each published container port: the variable naming its host port, and that port's default."""
    ports = {}
    for mapping in server()["ports"]:
        match = PORT.fullmatch(mapping)
        assert match, f"{mapping}: not host:${{OGMAP_..._PORT:-default}}:port"
        assert match["host"] == "127.0.0.1", mapping
        ports[int(match["container"])] = (match["variable"], int(match["default"]))
    return ports


def test_every_port_the_server_listens_on_is_published_on_loopback() -> None:
    loaded = configured()
    grpc_port = int(loaded.address.rsplit(":", 1)[1])
    assert loaded.address.startswith("0.0.0.0:") and loaded.live.foxglove_host == "0.0.0.0"
    listening = {grpc_port, loaded.live.web_port, loaded.live.foxglove_port}
    assert set(published()) == listening and len(listening) == 3 and 0 not in listening


def test_each_host_port_defaults_to_its_container_port_and_the_container_test_sets_it() -> None:
    ports = published()
    assert all(default == port for port, (_, default) in ports.items())
    variables = {variable for variable, _ in ports.values()}
    assert len(variables) == len(ports)
    script = CONTAINER_TEST.read_text()
    for variable in variables:  # the test publishes on free ports, not on ones the host may be using
        assert re.search(rf"\b{variable}\b", script), f"docker/container-test.sh does not set {variable}"


def test_the_health_check_asks_the_grpc_port_and_the_recordings_are_the_volume() -> None:
    loaded, service = configured(), server()
    grpc_port = loaded.address.rsplit(":", 1)[1]
    assert service["healthcheck"]["test"] == ["CMD", "python", "-m", "ogserver.healthcheck", f"127.0.0.1:{grpc_port}"]
    volumes = dict(volume.split(":") for volume in service["volumes"])
    assert volumes == {"recordings": loaded.record_dir}
    assert "recordings" in yaml.safe_load(COMPOSE.read_text())["volumes"]
    grace = loaded.grace_seconds + 2 * loaded.stop_timeout_seconds
    assert int(service["stop_grace_period"].removesuffix("s")) > grace  # SIGKILL only after a graceful stop


def test_the_build_names_the_runtime_stage_of_the_cpu_dockerfile() -> None:
    build = server()["build"]
    context = (COMPOSE.parent / build["context"]).resolve()
    assert context == REPO
    dockerfile = (context / build["dockerfile"]).read_text()
    assert re.search(rf"^FROM \S+ AS {build['target']}$", dockerfile, re.MULTILINE)
    assert "VOLUME /recordings" in dockerfile and 'ENTRYPOINT ["ogserver"]' in dockerfile


def reads_files(command: list[str]) -> bool:
    """Whether ``command`` is a compose provider with ``config``: podman-compose before 1.1 has none
    (``make container-test`` runs the file with it instead), and docker without its compose plugin
    answers ``docker compose config --help`` with its own help."""
    return bool(shutil.which(command[0])) and all(
        subprocess.run([*command, *arguments], capture_output=True).returncode == 0
        for arguments in (["version"], ["config", "--help"]))


PROVIDERS = [command for command in (["docker", "compose"], ["podman", "compose"], ["podman-compose"])
             if reads_files(command)]


@pytest.mark.skipif(not PROVIDERS, reason="no compose provider with `config` (docker compose, podman compose, "
                                          "podman-compose 1.1 or later)")
def test_a_compose_provider_reads_the_file_and_takes_the_host_ports_from_the_environment() -> None:
    environment = {variable: str(40000 + port) for port, (variable, _) in published().items()}
    result = subprocess.run([*PROVIDERS[0], "-f", str(COMPOSE), "config"], capture_output=True, text=True,
                            timeout=60, env={**os.environ, **environment})
    assert result.returncode == 0, result.stderr
    assert "ogserver.healthcheck" in result.stdout
    assert all(port in result.stdout for port in environment.values()), result.stdout
