"""The Triton kernels' modules for the tests (the loss's, the decode's): compiled on a GPU, interpreted on CPU
tensors without one.

Triton decides when a kernel is defined whether it is interpreted (``TRITON_INTERPRET=1`` then) and reads
the setting again when it runs one, so without a GPU the setting is made before the module is imported and
stays for the session; a session that imported it compiled and has no GPU skips with the reason.
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import statistics
import sys
from collections.abc import Callable
from types import ModuleType

import pytest
import torch

LOSS = "ogmapping.optim.triton_loss"
DECODE = "ogmapping.model.triton_decode"
HAS_TRITON = importlib.util.find_spec("triton") is not None
NO_TRITON = "triton is not installed (the dev extra installs it: pip install -e '.[dev]')"


def interpreted(module: ModuleType) -> bool:
    from triton.runtime.interpreter import InterpretedFunction

    return any(isinstance(value, InterpretedFunction) for value in vars(module).values())


def kernels(name: str) -> tuple[ModuleType, torch.device]:
    """Module ``name`` and the device its kernels take tensors on: CUDA where there is a GPU, else the CPU
    through the interpreter."""
    if not HAS_TRITON:
        pytest.skip(NO_TRITON)
    if name not in sys.modules and not torch.cuda.is_available():
        os.environ["TRITON_INTERPRET"] = "1"
    module = importlib.import_module(name)
    if interpreted(module):
        return module, torch.device("cpu")
    if not torch.cuda.is_available():
        pytest.skip("the Triton kernels were imported compiled in this pytest process and there is no GPU to run them")
    return module, torch.device("cuda")


def triton_loss() -> tuple[ModuleType, torch.device]:
    return kernels(LOSS)


def median_ms(step: Callable[[], None], repeats: int = 20) -> float:
    """The median time of ``step`` on the GPU (CUDA events), after three runs to warm up."""
    for _ in range(3):
        step()
    times = []
    for _ in range(repeats):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        step()
        end.record()
        end.synchronize()
        times.append(start.elapsed_time(end))
    return statistics.median(times)
