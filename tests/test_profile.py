"""One execution profile per mapper: device, backend, threads, and whether the Numba kernels run."""

from __future__ import annotations

import sys
from collections.abc import Callable

import numba
import numpy as np
import pytest
import torch

from ogmapping.config import resolve
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.mapper import Mapper
from ogmapping.render import gsplat_backend
from ogmapping.render.rules import ALPHA_MIN
from ogmapping.runtime.profile import execution_profile, resolve_device
from ogmapping.runtime.threads import torch_threads

SETTINGS = {"keyframes.first_iterations": 3, "keyframes.iterations": 1, "keyframes.frame_iterations": 1,
            "model.hash_log2_size": 12}
# Rasterizer, Gaussian assembly, fused loss, SSIM blur; a dense map adds the hash encoding and lazy Adam.
SPARSE_KERNELS = {"ogmapping.render.cpu_projection", "ogmapping.render.cpu_kernels", "ogmapping.model.gaussians_cpu",
                  "ogmapping.optim.fused_loss", "ogmapping.optim.ssim"}
COMPILED_MODULES = {"sparse": SPARSE_KERNELS,
                    "dense": SPARSE_KERNELS | {"ogmapping.model.encoding_cpu", "ogmapping.model.row_gradients",
                                               "ogmapping.optim.lazy_adam"}}


def test_compiled_kernels_run_on_the_cpu_with_the_cpu_backend_only(monkeypatch):
    cpu = execution_profile("cpu", "auto", "anchor")
    assert (cpu.device, cpu.backend, cpu.compiled, cpu.threads, cpu.precision) == (
        torch.device("cpu"), "cpu", True, 1, torch.float32)
    assert execution_profile("cpu", "cpu", "hash").threads is None
    reference = execution_profile("cpu", "torch", "anchor")
    assert (reference.backend, reference.compiled) == ("torch", False)
    monkeypatch.setattr(gsplat_backend, "unavailable_reason", lambda: "gsplat is not installed")
    with pytest.warns(RuntimeWarning, match="falls back to the pure-torch reference"):
        cuda = execution_profile("cuda", "auto", "anchor")
    assert cuda.backend == "torch" and not cuda.compiled and cuda.threads is None
    assert not execution_profile("cuda", "cpu", "anchor").compiled
    with pytest.raises(ValueError, match="unknown rasterizer backend"):
        execution_profile("cpu", "vulkan", "anchor")


def test_device_resolution(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == resolve_device("cpu") == torch.device("cpu")
    with pytest.raises(ValueError, match="CUDA is not available"):
        resolve_device("cuda")
    with pytest.raises(ValueError, match="device must be auto, cpu, cuda or cuda:N"):
        resolve_device("meta")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert resolve_device("auto") == resolve_device("cuda") == torch.device("cuda", 0)
    assert resolve_device("cuda:1") == torch.device("cuda", 1)
    with pytest.raises(ValueError, match="only 2 GPU"):
        resolve_device("cuda:2")


def _spy_on_numba_kernels(monkeypatch) -> list[str]:
    """Record every call of a Numba kernel held by an engine module (the entry points Python calls)."""
    calls: list[str] = []

    def recording(name: str, kernel: Callable) -> Callable:
        def call(*args, **kwargs):
            calls.append(name)
            return kernel(*args, **kwargs)
        return call

    for module_name, module in list(sys.modules.items()):
        if module_name.startswith("ogmapping"):
            for name, value in list(vars(module).items()):
                if isinstance(value, numba.core.dispatcher.Dispatcher):
                    monkeypatch.setattr(module, name, recording(f"{module_name}.{name}", value))
    return calls


def _map(preset: str, backend: str) -> tuple[list[float], np.ndarray]:
    """Two frames mapped, the first one's render. Two torch threads, whatever the machine has: a dense
    map's torch ops sum in an order that depends on the thread count, and over the training steps
    that rounding grows (16 threads put 0.4% of the pixels more than 1e-5 apart here, 1.25% on an
    H100 machine's 16 cores) without telling anything about the backends."""
    source = SyntheticSource(n_frames=2, width=40, height=30)
    with torch_threads(2):
        mapper = Mapper(resolve(preset, overrides={**SETTINGS, "backend": backend}))
        losses = [mapper.process(source[position]).loss for position in range(len(source))]
        frame = source[0]
        return losses, mapper.render(frame.c2w, frame.color_intrinsics).color


@pytest.mark.parametrize("preset", ["sparse", "dense"])
def test_torch_backend_on_the_cpu_runs_no_compiled_kernel(preset, monkeypatch):
    """backend=torch maps as backend=cpu does (to float32 rounding) without calling one Numba kernel."""
    compiled_losses, compiled_color = _map(preset, "cpu")  # loads and compiles every kernel before the spy
    calls = _spy_on_numba_kernels(monkeypatch)
    torch_losses, torch_color = _map(preset, "torch")
    assert calls == []
    _map(preset, "cpu")
    spied = {call.rsplit(".", 1)[0] for call in calls}
    assert COMPILED_MODULES[preset] <= spied, "the spy sees every compiled part of the cpu profile"
    np.testing.assert_allclose(torch_losses, compiled_losses, rtol=1e-5)
    # To float32 rounding, which may still tip a threshold (alpha at ALPHA_MIN, opacity at 0) the
    # other way in a pixel or two: such a pixel moves by less than ALPHA_MIN.
    difference = np.abs(torch_color - compiled_color)
    assert np.mean(difference > 1e-5) < 1e-3 and difference.max() < ALPHA_MIN
