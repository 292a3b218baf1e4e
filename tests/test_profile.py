"""One execution profile per mapper: device, backend, threads, and whether the Numba kernels run."""

from __future__ import annotations

import dataclasses
import sys
from collections.abc import Callable

import numba
import numpy as np
import pytest
import torch

from ogmapping.config import resolve
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.mapper import Mapper
from ogmapping.persist.state import MapState
from ogmapping.render import gsplat_backend
from ogmapping.render.rules import ALPHA_MIN
from ogmapping.runtime import profile
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


def test_the_triton_kernels_run_on_cuda_with_gsplat_where_triton_imports(monkeypatch):
    """The loss's kernels there; the decode's there too, for the static-shape step."""
    assert not execution_profile("cpu", "auto", "anchor").triton_loss
    assert not execution_profile("cpu", "auto", "anchor", "static").triton_decode
    monkeypatch.setattr(gsplat_backend, "unavailable_reason", lambda: None)
    monkeypatch.setattr(profile, "triton_unavailable_reason", lambda: None)
    cuda = execution_profile("cuda", "auto", "anchor")
    assert cuda.triton_loss and cuda.triton_decode and cuda.step_mode == "compiled"
    assert execution_profile("cuda", "auto", "anchor", "static").triton_decode
    assert not execution_profile("cuda", "auto", "anchor", "dynamic").triton_decode
    assert not execution_profile("cuda", "torch", "anchor").triton_loss
    assert not execution_profile("cuda", "torch", "anchor").triton_decode
    monkeypatch.setattr(profile, "triton_unavailable_reason", lambda: "triton is not installed")
    assert not execution_profile("cuda", "auto", "anchor").triton_loss
    assert not execution_profile("cuda", "auto", "anchor").triton_decode


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


def _source() -> SyntheticSource:
    return SyntheticSource(n_frames=2, width=40, height=30)


def _map(preset: str, backend: str) -> tuple[list[float], Mapper]:
    """Two frames mapped by a mapper with ``backend``: their losses and the mapper. Two torch threads,
    whatever the machine has, so that a dense map's torch sums split the same way on every machine."""
    source = _source()
    with torch_threads(2):
        mapper = Mapper(resolve(preset, overrides={**SETTINGS, "backend": backend}))
        return [mapper.process(source[position]).loss for position in range(len(source))], mapper


def _view(mapper: Mapper) -> np.ndarray:
    """The first frame's view of ``mapper``'s map, with two torch threads as ``_map``."""
    frame = _source()[0]
    with torch_threads(2):
        return mapper.render(frame.c2w, frame.color_intrinsics).color


def _render(state: MapState, backend: str) -> np.ndarray:
    """The first frame's view of the map ``state`` holds, rendered by a mapper with ``backend``."""
    config = dataclasses.replace(state.config, backend=backend)
    return _view(Mapper.from_state(dataclasses.replace(state, config=config)))


@pytest.mark.parametrize("preset", ["sparse", "dense"])
def test_torch_backend_on_the_cpu_runs_no_compiled_kernel(preset, monkeypatch):
    """backend=torch maps as backend=cpu does (to float32 rounding) without calling one Numba kernel."""
    compiled_losses, compiled = _map(preset, "cpu")  # loads and compiles every kernel before the spy
    calls = _spy_on_numba_kernels(monkeypatch)
    torch_losses, reference = _map(preset, "torch")
    state = compiled.state()
    same_map = _render(state, "torch")
    assert calls == []
    _map(preset, "cpu")
    spied = {call.rsplit(".", 1)[0] for call in calls}
    assert COMPILED_MODULES[preset] <= spied, "the spy sees every compiled part of the cpu profile"
    # One map rendered by each backend: the same image to float32 rounding, which may still tip a
    # threshold (alpha at ALPHA_MIN, opacity at 0) the other way in a pixel or two: such a pixel
    # moves by less than ALPHA_MIN.
    difference = np.abs(same_map - _render(state, "cpu"))
    assert np.mean(difference > 1e-5) < 1e-3 and difference.max() < ALPHA_MIN
    # Two maps, each trained by one backend. Adam (eps 1e-15) steps a value by up to its learning rate
    # however small its gradient, so the rounding of a gradient that nearly cancels moves the map by
    # more than rounding, and a later step may tip a threshold on it: how many pixels that reaches
    # depends on the CPU's kernels and thread count (up to 6 of these 3600 values more than 1e-5
    # apart, the largest 3.7e-5, with MKL's AVX-512 kernels on an Intel Xeon; none with its AVX2
    # ones). The losses still agree, the images on average to the rounding bar and everywhere to
    # less than ALPHA_MIN.
    np.testing.assert_allclose(torch_losses, compiled_losses, rtol=1e-5)
    difference = np.abs(_view(reference) - _view(compiled))
    assert difference.mean() < 1e-5 and difference.max() < ALPHA_MIN
