"""The machine a run happened on, without torch: CPU model and count, LLVM's name for the CPU, versions.

A figure is only comparable with another from the same machine, so every results.json names its
machine. This half needs no torch, so the torch-free client can name its machine too; every field
that cannot be read is None rather than an error.
"""

from __future__ import annotations

import os
import platform
from dataclasses import asdict, dataclass
from importlib import metadata
from pathlib import Path

CPUINFO = Path("/proc/cpuinfo")


@dataclass(frozen=True)
class Host:
    cpu_model: str | None  # /proc/cpuinfo's "model name" (what lscpu prints), else platform.processor()
    logical_cpus: int | None  # os.cpu_count(): every logical CPU the kernel sees
    usable_cpus: int | None  # the CPUs this process may run on (a container's or taskset's share)
    llvm_host_cpu: str | None  # what LLVM, and so Numba, compiles for: "znver3", "sapphirerapids"
    python: str
    numba: str | None

    def to_dict(self) -> dict:
        return asdict(self)


def cpu_model(cpuinfo: Path = CPUINFO) -> str | None:
    """The first "model name" of ``cpuinfo``; without one (not Linux, some ARM kernels), platform's answer."""
    try:
        for line in cpuinfo.read_text(errors="replace").splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and value.strip():
                return value.strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or None


def usable_cpus() -> int | None:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return None


def llvm_host_cpu() -> str | None:
    """Loads LLVM's library only when asked, so importing this module stays cheap."""
    try:
        import llvmlite.binding

        return llvmlite.binding.get_host_cpu_name() or None
    except Exception:  # an llvmlite that is missing or cannot load its library: the name is optional
        return None


def package_version(name: str) -> str | None:
    """An installed distribution's version, without importing it (importing gsplat may build kernels)."""
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return None


def host() -> Host:
    return Host(
        cpu_model=cpu_model(),
        logical_cpus=os.cpu_count(),
        usable_cpus=usable_cpus(),
        llvm_host_cpu=llvm_host_cpu(),
        python=platform.python_version(),
        numba=package_version("numba"),
    )
