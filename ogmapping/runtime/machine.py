"""The machine a run happened on, with torch: the host, torch's build and threads, gsplat, the GPU.

``machine(device)`` is what ``ogmap run`` writes as results.json's ``machine``. Nothing here
raises: a GPU property, the driver's version or gsplat that cannot be read is None.
"""

from __future__ import annotations

import subprocess
from dataclasses import asdict, dataclass

import torch

from ogmapping.runtime.host import Host, host, package_version

DRIVER_QUERY = ["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"]


@dataclass(frozen=True)
class Gpu:
    name: str
    memory_bytes: int
    compute_capability: str  # "9.0" for an H100
    count: int  # GPUs torch sees
    cuda: str | None  # the CUDA version torch was built with (torch.version.cuda)
    driver: str | None  # the NVIDIA driver's version, from nvidia-smi


@dataclass(frozen=True)
class Machine:
    host: Host
    torch: str
    torch_threads: int  # torch.get_num_threads() of the calling thread
    gsplat: str | None
    gpu: Gpu | None  # the run's GPU; on a CPU run, the first GPU when CUDA is available

    def to_dict(self) -> dict:
        """Flat: the host's fields beside torch's, ``gpu`` a nested record or None."""
        fields = asdict(self)
        return {**fields.pop("host"), **fields}


def driver_version() -> str | None:
    try:
        result = subprocess.run(DRIVER_QUERY, capture_output=True, text=True, timeout=10, check=True)
    except (OSError, subprocess.SubprocessError):
        return None
    lines = result.stdout.split()
    return lines[0] if lines else None


def gpu(device: torch.device) -> Gpu | None:
    try:
        if not torch.cuda.is_available():
            return None
        index = device.index if device.type == "cuda" and device.index is not None else 0
        properties = torch.cuda.get_device_properties(index)
        return Gpu(
            name=properties.name,
            memory_bytes=int(properties.total_memory),
            compute_capability=f"{properties.major}.{properties.minor}",
            count=torch.cuda.device_count(),
            cuda=torch.version.cuda,
            driver=driver_version(),
        )
    except Exception:  # a broken driver or a lost device: the record is optional, the run's figures are not
        return None


def machine(device: torch.device) -> Machine:
    return Machine(
        host=host(),
        torch=torch.__version__,
        torch_threads=torch.get_num_threads(),
        gsplat=package_version("gsplat"),
        gpu=gpu(device),
    )
