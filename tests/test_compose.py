"""docker/compose.yaml agrees with the server and the image: its command is flags ogserver accepts, every
port the server listens on is published (on the host's loopback), the health check asks the gRPC port,
the record dir is the volume, and the build names a stage of the Dockerfile. Where a compose provider is
installed, it reads the file too."""

from __future__ import annotations

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


def server() -> dict[str, Any]:
    return yaml.safe_load(COMPOSE.read_text())["services"]["server"]


def configured() -> settings.Settings:
    """The settings the compose command gives the server (refuses unknown flags and invalid values)."""
    flags = {key: value for key, value in vars(parser().parse_args(server()["command"])).items()
             if key not in ("config", "log_level")}
    loaded = settings.load(None, flags)
    loaded.validate()
    return loaded


def test_every_port_the_server_listens_on_is_published_on_loopback() -> None:
    loaded = configured()
    grpc_port = int(loaded.address.rsplit(":", 1)[1])
    assert loaded.address.startswith("0.0.0.0:") and loaded.live.foxglove_host == "0.0.0.0"
    listening = {grpc_port, loaded.live.web_port, loaded.live.foxglove_port}
    published = {}
    for mapping in server()["ports"]:
        host, host_port, container_port = mapping.split(":")
        assert host == "127.0.0.1", mapping
        published[int(container_port)] = int(host_port)
    assert set(published) == listening and len(listening) == 3 and 0 not in listening


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


PROVIDERS = [command for command in (["docker", "compose"], ["podman", "compose"], ["podman-compose"])
             if shutil.which(command[0]) and subprocess.run([*command, "version"], capture_output=True).returncode == 0]


@pytest.mark.skipif(not PROVIDERS, reason="no compose provider (docker compose, podman compose, podman-compose)")
def test_a_compose_provider_reads_the_file() -> None:
    result = subprocess.run([*PROVIDERS[0], "-f", str(COMPOSE), "config"], capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 0, result.stderr
    assert "8765" in result.stdout and "ogserver.healthcheck" in result.stdout
