"""deploy/kuberay's manifests agree with the server and with each other: parsed with yaml.safe_load,
the server's settings loaded and checked as ogserver would, names, ports, volumes and resources
cross-checked. Nothing here runs Kubernetes or KubeRay."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
import yaml
from ogserver import settings

ROOT = Path(__file__).resolve().parents[1]
KUBERAY = ROOT / "deploy" / "kuberay"
HEALTHCHECK = ["python", "-m", "ogserver.healthcheck"]


def manifests() -> dict[tuple[str, str], dict[str, Any]]:
    """Every document of every file, by (kind, name)."""
    found = {}
    for path in sorted(KUBERAY.glob("*.yaml")):
        for document in yaml.safe_load_all(path.read_text()):
            found[(document["kind"], document["metadata"]["name"])] = document
    return found


@pytest.fixture(scope="module")
def docs() -> dict[tuple[str, str], dict[str, Any]]:
    return manifests()


@pytest.fixture(scope="module")
def server(docs, tmp_path_factory: pytest.TempPathFactory) -> settings.Settings:
    config = tmp_path_factory.mktemp("kuberay") / "server.yaml"
    config.write_text(docs[("ConfigMap", "ogmapping-cluster-config")]["data"]["server.yaml"])
    return settings.load(config)  # refuses unknown names, wrong types and invalid values


def by_name(items: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    return {item["name"]: item for item in items}


def test_every_kind_is_there_once(docs) -> None:
    assert sorted(docs) == [
        ("ConfigMap", "ogmapping-cluster-config"), ("Deployment", "ogmapping-frontend"),
        ("PersistentVolumeClaim", "ogmapping-cluster-recordings"), ("RayCluster", "ogmapping"),
        ("Secret", "ogmapping-s3"), ("Service", "ogmapping-cluster"),
    ]


def test_the_front_ends_join_the_ray_cluster_through_its_head_service(docs, server) -> None:
    ray_cluster = docs[("RayCluster", "ogmapping")]
    head = ray_cluster["spec"]["headGroupSpec"]
    client_port = by_name(head["template"]["spec"]["containers"][0]["ports"])["client"]["containerPort"]
    assert server.cluster == f"ray://{ray_cluster['metadata']['name']}-head-svc:{client_port}"
    assert head["rayStartParams"]["num-cpus"] == "0", "sessions must stay off the head node"
    pinned = re.search(r'"ray==([\d.]+)"', (ROOT / "pyproject.toml").read_text())
    assert pinned and ray_cluster["spec"]["rayVersion"] == pinned[1]


def test_the_service_balances_several_front_ends_on_the_servers_port(docs, server) -> None:
    deployment = docs[("Deployment", "ogmapping-frontend")]
    service = docs[("Service", "ogmapping-cluster")]
    pod = deployment["spec"]["template"]
    container = pod["spec"]["containers"][0]
    port = by_name(container["ports"])["grpc"]["containerPort"]
    assert deployment["spec"]["replicas"] >= 2
    assert server.address == f"0.0.0.0:{port}"
    assert service["spec"]["ports"][0]["targetPort"] == "grpc"
    assert service["spec"]["selector"].items() <= pod["metadata"]["labels"].items()
    assert deployment["spec"]["selector"]["matchLabels"].items() <= pod["metadata"]["labels"].items()
    mount = by_name(container["volumeMounts"])["config"]["mountPath"]
    assert container["args"] == ["--config", f"{mount}/server.yaml"]
    for probe in ("startupProbe", "readinessProbe", "livenessProbe"):
        assert container[probe]["exec"]["command"] == [*HEALTHCHECK, f"127.0.0.1:{port}"]
    assert pod["spec"]["terminationGracePeriodSeconds"] > server.grace_seconds


def test_every_pod_that_writes_or_reads_sessions_mounts_the_shared_volume_at_the_record_dir(docs, server) -> None:
    claim = docs[("PersistentVolumeClaim", "ogmapping-cluster-recordings")]
    assert claim["spec"]["accessModes"] == ["ReadWriteMany"]
    workers = docs[("RayCluster", "ogmapping")]["spec"]["workerGroupSpecs"]
    pods = [group["template"]["spec"] for group in workers]
    pods.append(docs[("Deployment", "ogmapping-frontend")]["spec"]["template"]["spec"])
    for pod in pods:
        volume = next(volume for volume in pod["volumes"] if "persistentVolumeClaim" in volume)
        assert volume["persistentVolumeClaim"]["claimName"] == claim["metadata"]["name"]
        mounted = {mount["name"]: mount["mountPath"] for mount in pod["containers"][0]["volumeMounts"]}
        assert mounted[volume["name"]] == server.record_dir


def test_the_gpu_workers_can_take_the_sessions_the_front_ends_ask_for(docs, server) -> None:
    (group,) = docs[("RayCluster", "ogmapping")]["spec"]["workerGroupSpecs"]
    spec = group["template"]["spec"]
    limits = spec["containers"][0]["resources"]["limits"]
    assert int(limits["nvidia.com/gpu"]) >= 1 and 0 < server.session_gpus <= int(limits["nvidia.com/gpu"])
    assert server.session_cpus <= float(limits["cpu"])
    assert {"key": "nvidia.com/gpu", "operator": "Exists", "effect": "NoSchedule"} in spec["tolerations"]
    secret = docs[("Secret", "ogmapping-s3")]["metadata"]["name"]
    assert {"secretRef": {"name": secret, "optional": True}} in spec["containers"][0]["envFrom"]
    assert group["minReplicas"] <= group["replicas"] <= group["maxReplicas"]
