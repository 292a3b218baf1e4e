"""results.json names the machine a run happened on, and naming it never fails a run."""

from __future__ import annotations

import json

import pytest
import torch

from ogmapping.cli.runner import RunOptions, run
from ogmapping.config import resolve
from ogmapping.runtime import host as host_module
from ogmapping.runtime import machine as machine_module
from ogmapping.runtime.host import cpu_model, host
from ogmapping.runtime.machine import machine

HOST_TYPES = {"cpu_model": str, "logical_cpus": int, "usable_cpus": int, "llvm_host_cpu": str, "python": str,
              "numba": str}
GPU_TYPES = {"name": str, "memory_bytes": int, "compute_capability": str, "count": int, "cuda": (str, type(None)),
             "driver": (str, type(None))}


def check_host_fields(record: dict) -> None:
    for key, kind in HOST_TYPES.items():
        assert isinstance(record[key], kind), (key, record[key])


def test_ogmap_run_writes_the_machine(tmp_path):
    options = RunOptions(data="synthetic", format="synthetic", frames="0:4", scale=0.25, device="cpu",
                         out=tmp_path, progress=False)
    run(options, resolve("sparse", overrides={"keyframes.first_iterations": "3", "keyframes.iterations": "2"}))
    record = json.loads((tmp_path / "results.json").read_text())["machine"]
    check_host_fields(record)
    assert record["torch"] == torch.__version__
    assert isinstance(record["torch_threads"], int) and record["torch_threads"] >= 1
    assert record["gsplat"] is None or isinstance(record["gsplat"], str)
    if torch.cuda.is_available():
        for key, kind in GPU_TYPES.items():
            assert isinstance(record["gpu"][key], kind), (key, record["gpu"][key])
    else:
        assert record["gpu"] is None


def test_without_cuda_the_gpu_is_none(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    record = machine(torch.device("cpu")).to_dict()
    assert record["gpu"] is None
    json.dumps(record)


def test_an_unreadable_gpu_or_driver_is_none(monkeypatch):
    def broken(index):
        raise RuntimeError("CUDA driver initialization failed")

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_device_properties", broken)
    assert machine(torch.device("cuda", 0)).gpu is None
    monkeypatch.setattr(machine_module, "DRIVER_QUERY", ["/nonexistent/nvidia-smi"])
    assert machine_module.driver_version() is None


def test_cpu_model_from_cpuinfo_or_platform(tmp_path, monkeypatch):
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("processor\t: 0\nvendor_id\t: AuthenticAMD\nmodel name\t: AMD EPYC 9554 64-Core Processor\n")
    assert cpu_model(cpuinfo) == "AMD EPYC 9554 64-Core Processor"
    monkeypatch.setattr(host_module.platform, "processor", lambda: "aarch64")
    cpuinfo.write_text("processor\t: 0\nCPU part\t: 0xd0c\n")
    assert cpu_model(cpuinfo) == "aarch64"
    assert cpu_model(tmp_path / "missing") == "aarch64"


@pytest.mark.parametrize("failure", [ImportError, OSError])
def test_the_host_record_survives_a_missing_llvm(monkeypatch, failure):
    import llvmlite.binding

    def broken():
        raise failure("no LLVM")

    monkeypatch.setattr(llvmlite.binding, "get_host_cpu_name", broken)
    record = host().to_dict()
    assert record["llvm_host_cpu"] is None
    assert isinstance(record["logical_cpus"], int)
