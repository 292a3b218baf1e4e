"""The torch operators one optimisation step dispatches, held under a budget.

On a GPU each operator is at least one kernel launch and its host-side dispatch, so a step of a
small map costs what it dispatches, not what it computes; a change that adds operators to the step
slows the GPU path even where the CPU's timings do not show it. The budgets are bars, each set a
little above the count noted beside it (a 2-core Intel Xeon VM, family 6 model 167, torch 2.13.0+cpu). A change
that raises a count must lower it again or argue for the new budget with figures (the step's time
on the CPU and, where one is at hand, the GPU).
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager

import pytest
from steady_step import mapped
from torch.utils._python_dispatch import TorchDispatchMode

from ogmapping.mapper import Mapper
from ogmapping.runtime.threads import torch_threads

# Operators per step with the window rendered as one batch: 1346 with ``cpu`` (the compiled kernels
# dispatch none themselves; backward 476, decode 336, optimizer 224, rasterize 135, loss 93), 1144
# with ``cpu`` and the decoders run once per window as on a GPU (backward 321, decode 289), and 23557
# with ``torch`` (the reference rasterizer, forward 7752 and most of backward's 14809, loops over the
# tiles Gaussians reach, so its count also follows the scene).
BUDGETS = {"cpu": 1400, "cpu-shared-decode": 1180, "torch": 24400}


class DispatchCount(TorchDispatchMode):
    """Every operator dispatched below autograd (forward and backward), by the mapper's stage."""

    def __init__(self) -> None:
        super().__init__()
        self.stage = "other"
        self.by_stage: Counter[str] = Counter()
        self.by_operator: Counter[str] = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.by_stage[self.stage] += 1
        self.by_operator[str(func)] += 1
        return func(*args, **(kwargs or {}))

    @property
    def total(self) -> int:
        return sum(self.by_stage.values())


def staged(mapper: Mapper, count: DispatchCount):
    """``mapper.model.timed`` that also tells ``count`` which stage is running."""
    timed = mapper.model.timed

    @contextmanager
    def stage(name: str) -> Iterator[None]:
        outer, count.stage = count.stage, name
        try:
            with timed(name):
                yield
        finally:
            count.stage = outer

    return stage


def steady_step_count(case: str, monkeypatch: pytest.MonkeyPatch) -> DispatchCount:
    """The operators of one step on the next frame's view and the two newest keyframes, counted
    after an uncounted step on the same (so constants cached on first use are not counted)."""
    backend, _, shared = case.partition("-")
    mapper, view, window = mapped("sparse", {"backend": backend}, shared_decode=bool(shared))
    count = DispatchCount()
    monkeypatch.setattr(mapper.model, "timed", staged(mapper, count))
    with torch_threads(mapper.profile.threads):
        mapper.steps.step(view, window)
        with count:
            mapper.steps.step(view, window)
    return count


@pytest.mark.parametrize("case", BUDGETS)
def test_a_step_dispatches_no_more_operators_than_its_budget(case, monkeypatch):
    count = steady_step_count(case, monkeypatch)
    assert count.total <= BUDGETS[case], (
        f"{case}: {count.total} operators per step, budget {BUDGETS[case]}; by stage "
        f"{dict(count.by_stage.most_common())}; most dispatched {count.by_operator.most_common(12)}"
    )
