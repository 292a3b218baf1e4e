"""The stage timer on CUDA: recording and querying its events is no host synchronisation."""

from __future__ import annotations

import pytest
import torch

from ogmapping.runtime.stage_timer import StageTimer

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")]


def test_timed_stages_pass_the_sync_debug_mode() -> None:
    timer = StageTimer.for_device(torch.device("cuda"))
    x = torch.randn(512, 512, device="cuda")
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        for _ in range(50):
            with timer.stage("matmul"):
                x = torch.tanh(x @ x)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert 0 < timer.pending <= 50
    assert timer.totals()["matmul"] > 0 and timer.pending == 0
