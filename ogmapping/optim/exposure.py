"""Per-keyframe exposure (``keyframes.exposure``): an affine colour correction of a view's render,
learned with the map, as MonoGS does.

A camera's auto-exposure makes two views of one surface differ in brightness; with one colour per
surface, each view that comes later rewrites what the earlier ones taught the map, and the map
forgets. With the switch on, each keyframe but the first, and the streamed view during its steps,
carries two learnable scalars (a, b): its loss (colour L1 and SSIM) compares exp(a) * render + b, one
a and one b per image shared by the three channels, with the view's colour, so (a, b) explain the
view's exposure instead of the map. The first keyframe has none (the identity): it fixes the map's
colour scale, and renders for clients, exports and evaluation show the map itself, uncorrected.

The scalars are a parameter group of the map's Adam (``GROUP``, at ``optim.exposure_lr``), each view's
a leaf tensor of its own: a keyframe's joins the group when the keyframe is inserted and stays, a
streamed frame's leaves it after the frame's steps. The group thus holds the keyframes' in keyframe
order (a checkpoint keys Adam's moments by position), a streamed frame's last.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

import torch

from ogmapping.runtime.device_constants import on_device

GROUP = "exposure"  # the name of the Adam group
STATE_SIZE = 2  # (a, b)
IDENTITY = torch.zeros(STATE_SIZE)  # a view without its own exposure (the first keyframe)


class Exposure:
    """One view's (a, b), initialised at the identity (0, 0)."""

    def __init__(self, device: torch.device | str) -> None:
        self.values = torch.zeros(STATE_SIZE, device=device, requires_grad=True)

    def state(self) -> torch.Tensor:
        """(a, b) as float64 on the host (for checkpoints)."""
        return self.values.detach().double().cpu()

    @classmethod
    def from_state(cls, row: torch.Tensor, device: torch.device | str) -> Exposure:
        """The exposure a ``state`` row holds; ValueError when it is not one."""
        if row.shape != (STATE_SIZE,) or not bool(torch.isfinite(row).all()):
            raise ValueError(f"an exposure is {STATE_SIZE} finite numbers, got shape {tuple(row.shape)}")
        exposure = cls(device)
        with torch.no_grad():
            exposure.values.copy_(row)
        return exposure


def exposed(colour: torch.Tensor, exposure: torch.Tensor) -> torch.Tensor:
    """exp(a) * colour + b: ``colour`` (H, W, 3) with ``exposure`` (2,), or (B, H, W, 3) with (B, 2)."""
    a, b = exposure.unbind(-1)
    shape = a.shape + (1,) * (colour.dim() - a.dim())
    return torch.exp(a).reshape(shape) * colour + b.reshape(shape)


def values_of(exposure: Exposure | None, device: torch.device) -> torch.Tensor:
    """A view's (a, b) as the loss takes them: its own, or the identity (a shared constant) without."""
    return exposure.values if exposure is not None else on_device(IDENTITY, device, torch.float32)


def _group(optimizer: torch.optim.Optimizer) -> dict:
    for group in optimizer.param_groups:
        if group.get("name") == GROUP:
            return group
    raise ValueError(f"the optimiser has no {GROUP!r} group: keyframes.exposure is off")


def join(optimizer: torch.optim.Optimizer, exposure: Exposure) -> None:
    """``exposure`` is stepped with the map from now on (last in the group)."""
    _group(optimizer)["params"].append(exposure.values)


def leave(optimizer: torch.optim.Optimizer, exposure: Exposure) -> None:
    """``exposure`` is no longer stepped; Adam forgets its moments."""
    params = _group(optimizer)["params"]
    params[:] = [param for param in params if param is not exposure.values]
    optimizer.state.pop(exposure.values, None)


@contextmanager
def stepped(optimizer: torch.optim.Optimizer, exposure: Exposure | None, keep: bool,
            lock: threading.RLock) -> Iterator[None]:
    """``exposure`` (none: nothing) in the optimiser for the block, and after it too when ``keep`` (a
    keyframe's); ``lock`` (the mapper's) held while the group changes."""
    if exposure is None:
        yield
        return
    with lock:
        join(optimizer, exposure)
    try:
        yield
    finally:
        if not keep:
            with lock:
                leave(optimizer, exposure)
