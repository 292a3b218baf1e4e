"""deploy/'s Kubernetes manifests agree with the server and with each other.

docker/container-test.sh plays common.yaml + cpu.yaml with `podman kube play`. The GPU variant cannot
run here, so these checks hold it to the CPU one: the same pod but for the image, --device, the
resources and the GPU toleration.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import pytest
import yaml
from ogserver import settings

DEPLOY = Path(__file__).resolve().parents[1] / "deploy"
VARIANTS = ("cpu.yaml", "gpu.yaml")


def documents(name: str) -> dict[str, dict[str, Any]]:
    return {document["kind"]: document for document in yaml.safe_load_all((DEPLOY / name).read_text())}


def pod(name: str) -> dict[str, Any]:
    return documents(name)["Deployment"]["spec"]["template"]["spec"]


def mounts(container: dict[str, Any]) -> dict[str, str]:
    return {mount["name"]: mount["mountPath"] for mount in container["volumeMounts"]}


@pytest.mark.parametrize("variant", VARIANTS)
def test_the_config_map_configures_the_server_the_pod_runs(variant: str, tmp_path: Path) -> None:
    common = documents("common.yaml")
    spec = pod(variant)
    server = spec["containers"][0]
    config = tmp_path / "server.yaml"
    config.write_text(common["ConfigMap"]["data"]["server.yaml"])
    loaded = settings.load(config)  # refuses unknown names and wrong types
    loaded.validate()
    assert loaded.address == f"0.0.0.0:{server['ports'][0]['containerPort']}"
    assert loaded.record_dir == mounts(server)["recordings"]
    assert server["args"][:2] == ["--config", f"{mounts(server)['config']}/server.yaml"]
    volumes = {volume["name"]: volume for volume in spec["volumes"]}
    assert volumes["config"]["configMap"]["name"] == common["ConfigMap"]["metadata"]["name"]
    assert volumes["recordings"]["persistentVolumeClaim"]["claimName"] == \
        common["PersistentVolumeClaim"]["metadata"]["name"]
    assert common["Service"]["spec"]["ports"][0]["targetPort"] == server["ports"][0]["name"]
    assert spec["terminationGracePeriodSeconds"] > loaded.grace_seconds


@pytest.mark.parametrize("variant", VARIANTS)
def test_every_probe_asks_the_grpc_health_service(variant: str) -> None:
    server = pod(variant)["containers"][0]
    port = server["ports"][0]["containerPort"]
    for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
        assert server[probe]["exec"]["command"] == ["python", "-m", "ogserver.healthcheck", f"127.0.0.1:{port}"]


def without_the_device(deployment: dict[str, Any]) -> dict[str, Any]:
    """The Deployment less what a GPU variant changes on purpose."""
    stripped = copy.deepcopy(deployment)
    for labels in (stripped["metadata"]["labels"], stripped["spec"]["template"]["metadata"]["labels"]):
        labels.pop("variant")
    spec = stripped["spec"]["template"]["spec"]
    spec.pop("tolerations", None)
    server = spec["containers"][0]
    for key in ("image", "resources"):
        server.pop(key)
    server["args"] = server["args"][:-1]  # --device's value
    return stripped


def test_the_gpu_variant_is_the_cpu_one_on_a_gpu() -> None:
    cpu, gpu = (documents(variant)["Deployment"] for variant in VARIANTS)
    assert without_the_device(gpu) == without_the_device(cpu)
    server = gpu["spec"]["template"]["spec"]["containers"][0]
    assert server["args"][-2:] == ["--device", "cuda"] and server["resources"]["limits"]["nvidia.com/gpu"] == 1
    assert cpu["spec"]["template"]["spec"]["containers"][0]["args"][-2:] == ["--device", "cpu"]
