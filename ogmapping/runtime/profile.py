"""How a mapper runs, chosen once: device, rasterizer backend, precision, torch threads, compiled kernels,
static shapes.

Every choice that depends on where the map lives is made here, when the mapper is built, and
passed down as flags: the modules the mapper calls never look at a tensor's device to pick a code
path, so one session cannot mix the two halves of a choice. The rule for the Numba kernels
(rasterizer, Gaussian assembly, hash encoding, fused loss, SSIM blur, lazy Adam's step): they run
iff the device is the CPU and the backend resolves to ``cpu``, so ``backend="torch"`` on the CPU
runs the pure-torch reference end to end. ``auto`` resolves as ``render.resolve_backend`` does:
``cpu`` on the CPU, ``gsplat`` on CUDA when it can render there, else ``torch`` (with a warning).
The GPU's counterpart of the fused loss, its Triton kernels, runs iff the device is CUDA, the backend
``gsplat`` and triton importable; ``backend="torch"`` there too keeps the reference end to end. The fused
decode's Triton kernels (``ogmapping.model.triton_decode``) run by the same rule, for the static-shape step.
Frames are prepared (depth registered and clipped) on the device iff it is CUDA.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ogmapping.render import resolve_backend


@dataclass(frozen=True)
class ExecutionProfile:
    """One mapper's execution choices; built by ``execution_profile``."""

    device: torch.device
    backend: str  # concrete rasterizer backend: one of backends.BACKENDS
    compiled: bool  # whether the Numba CPU kernels run instead of their torch definitions
    threads: int | None  # torch threads for the mapper's calls; None leaves the caller's setting
    precision: torch.dtype = torch.float32  # of frames and poses; the only one the compiled kernels take
    # Decoders run once per step's window, not once per view: fewer, larger kernels on a GPU. On the
    # CPU it is no faster (bench/RESULTS.md "Batched windows") and would change every CPU map's rounding.
    shared_decode: bool = False
    # Every view decodes every row of the anchor buffers, the ones not drawn inert (``static_gaussians``):
    # no selection makes the host wait for the device, and a step's shapes stay put between capacity
    # doublings. On the CPU it decodes rows it would not draw, for nothing to wait on.
    static_shapes: bool = False
    # The static-shape step's torch work runs as compiled graphs (``ogmapping.mapping.graphs``).
    graphs: bool = False
    # The loss's image terms come from the Triton kernels (``ogmapping.optim.triton_loss``), not autograd.
    triton_loss: bool = False
    # The static-shape decode comes from the Triton kernels (``ogmapping.model.triton_decode``), not autograd.
    triton_decode: bool = False
    # Frames uploaded as they come and registered and clipped on the device (``ogmapping.mapping.prepared``),
    # leaving the host only the copy into pinned memory. On the CPU numpy's registration, the reference, stays: it is
    # faster there (bench/RESULTS.md "Frames prepared ahead").
    device_frames: bool = False

    @property
    def step_mode(self) -> str:
        """What ``config.step`` resolved to: ``compiled``, ``static`` or ``dynamic``."""
        return "compiled" if self.graphs else "static" if self.static_shapes else "dynamic"


def execution_profile(device: str | torch.device, backend: str, encoding: str,
                      step: str = "auto") -> ExecutionProfile:
    """The profile of a mapper on ``device`` with ``config.backend``, ``config.model.encoding`` and
    ``config.step``. Static shapes run the decode in torch ops (as on CUDA), so not the Numba kernels."""
    device = torch.device(device)
    concrete = resolve_backend(backend, device)
    step = ("compiled" if device.type == "cuda" else "dynamic") if step == "auto" else step
    static = step in ("static", "compiled")
    triton = device.type == "cuda" and concrete == "gsplat" and triton_unavailable_reason() is None
    return ExecutionProfile(
        device=device,
        backend=concrete,
        compiled=device.type == "cpu" and concrete == "cpu" and not static,
        threads=_mapping_threads(device, encoding),
        shared_decode=device.type == "cuda" or static,
        static_shapes=static,
        graphs=step == "compiled",
        triton_loss=triton,
        triton_decode=triton and static,
        device_frames=device.type == "cuda",
    )


def triton_unavailable_reason() -> str | None:
    """Why the Triton kernels (the loss's, ``ogmapping.optim.triton_loss``, and the decode's,
    ``ogmapping.model.triton_decode``) cannot run here, or None: they need triton (on CUDA, torch's own)."""
    try:
        import triton  # noqa: F401
    except ImportError as error:
        return f"triton is not installed ({error})"
    return None


def _mapping_threads(device: torch.device, encoding: str) -> int | None:
    """One torch thread where every op is small: a sparse map on the CPU.

    A sparse map on the CPU runs only small torch ops around the compiled kernels (decoders over a
    few thousand anchors, gathers, Adam over the anchors); with a second torch thread each of them
    pays to wake it, and a (1800 x 36) @ (36 x 32) matmul takes 3-4x longer than on one thread
    (bench/RESULTS.md). A dense map's hash table (2^19 entries per level) is large enough to want
    every thread, as does anything on CUDA.
    """
    return 1 if device.type == "cpu" and encoding == "anchor" else None


def resolve_device(name: str) -> torch.device:
    """``auto`` is the first GPU when there is one, else the CPU; an unusable explicit choice fails
    now (``ValueError``), not when the first frame arrives."""
    if name == "auto":
        return torch.device("cuda:0" if torch.cuda.is_available() else "cpu")
    device = torch.device(name)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"device {name!r} requested but CUDA is not available")
        if (device.index or 0) >= torch.cuda.device_count():
            raise ValueError(f"device {name!r} requested but only {torch.cuda.device_count()} GPU(s) exist")
        return torch.device("cuda", device.index or 0)
    if device.type != "cpu":
        raise ValueError(f"device must be auto, cpu, cuda or cuda:N (got {name!r})")
    return torch.device("cpu")
