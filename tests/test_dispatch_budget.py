"""The torch operators one optimisation step dispatches, held under a budget.

On a GPU each operator is at least one kernel launch and its host-side dispatch, so a step of a
small map costs what it dispatches, not what it computes; a change that adds operators to the step
slows the GPU path even where the CPU's timings do not show it. The budgets are bars, each set a
little above the count noted beside it (a 2-core Intel Xeon VM, family 6 model 167, torch 2.13.0+cpu). A change
that raises a count must lower it again or argue for the new budget with figures (the step's time
on the CPU and, where one is at hand, the GPU).
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager

import pytest
import torch
from steady_step import mapped
from torch.utils._python_dispatch import TorchDispatchMode

from ogmapping.mapper import Mapper
from ogmapping.optim.keyframes import Keyframe, View
from ogmapping.optim.poses import PoseCorrection
from ogmapping.runtime.threads import torch_threads

# Operators per step with the window rendered as one batch, ``sparse`` refining its keyframes' poses: 1291 with
# ``cpu`` (each of the rasterizer's Numba stages one operator, ``torch.library``; backward 473, decode 315,
# optimizer 244, loss 81, window 71: the window's poses one batch, ``optim.window_poses``; statistics 69,
# rasterize 34), 1089 with ``cpu`` and the decoders run once per window as on a GPU (decode 268, backward 318),
# and 23694 with ``torch`` (the reference rasterizer, forward 7695 and most of backward's 14935, loops over the
# tiles Gaussians reach, so its count also follows the scene). Without refinement 1195 and 993.
BUDGETS = {"cpu": 1300, "cpu-shared-decode": 1100, "torch": 24400}
# The static-shape step as compiled graphs (config step=compiled), counted by the profiler: each operator
# called outside a graph, each of the graphs' fused kernels and each rasterizer stage once. 233 on the
# machine above (backward 107, decode 33, rasterize 31, optimizer 21: fused Adam's two per parameter group
# and the pose corrections' step, loss 18, window 16); 221 without refinement; dense 284.
COMPILED_BUDGET = 250


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
    return counted_step(*mapped("sparse", {"backend": backend}, shared_decode=bool(shared)), monkeypatch)


def counted_step(mapper: Mapper, view: View, window: list[Keyframe], monkeypatch: pytest.MonkeyPatch) -> DispatchCount:
    """The operators of a step of ``mapper`` on ``view`` and ``window``, after an uncounted one."""
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


def test_a_refining_step_dispatches_the_same_however_many_corrections_it_moves(monkeypatch):
    """With ``poses.refine`` a step's poses are one batch and its corrections' steps one step: the view's correction
    moving too (``poses.view_steps``) adds no operator to a step that moves a keyframe's."""
    counts = {}
    for view_steps in ("false", "true"):
        overrides = {"backend": "cpu", "poses.refine": "true", "poses.track_iterations": "0",
                     "poses.view_steps": view_steps}
        mapper, view, window = mapped("sparse", overrides)
        view = dataclasses.replace(view, correction=PoseCorrection("cpu"))
        moving = [drawn for drawn in (view, *window) if drawn.correction is not None
                  and mapper.steps.moves(drawn.correction, view)]
        counts[len(moving)] = counted_step(mapper, view, window, monkeypatch).total
    assert set(counts) == {1, 2}, counts
    assert counts[2] <= counts[1], counts


def compiled_step_count(preset: str) -> tuple[Counter[str], Counter[str]]:
    """Operators and fused kernels of one compiled steady step (profiler), by name and by stage."""
    mapper, view, window = mapped(preset, {"refine.interval": "10000"}, step="compiled")
    timed = mapper.model.timed

    @contextmanager
    def stage(name: str) -> Iterator[None]:
        with torch.profiler.record_function(STAGE + name), timed(name):
            yield

    mapper.model.timed = stage
    torch._dynamo.reset()  # compiled afresh here, with each kernel visible to the profiler
    with torch._inductor.config.patch({"cpp.enable_kernel_profile": True}), torch_threads(mapper.profile.threads):
        for _ in range(2):
            mapper.steps.step(view, window)
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU]) as profile:
            mapper.steps.step(view, window)
    by_name, by_stage = Counter(), Counter()
    for event in profile.events():
        if _dispatched(event) and not any(_dispatched(outer) for outer in _enclosing(event)):
            by_name[event.name] += 1
            by_stage[next((outer.name[len(STAGE):] for outer in _enclosing(event) if outer.name.startswith(STAGE)),
                          "other")] += 1
    return by_name, by_stage


STAGE = "stage "


def _dispatched(event) -> bool:
    """An operator (aten, or one of the CPU rasterizer's) or one of Inductor's fused CPU kernels."""
    return event.name.startswith(("aten::", "ogmapping::")) or "cpp_fused" in event.name


def _enclosing(event):
    parent = event.cpu_parent
    while parent is not None:
        yield parent
        parent = parent.cpu_parent


def test_a_compiled_step_dispatches_within_its_budget_and_never_waits():
    by_name, by_stage = compiled_step_count("sparse")
    kernels = sum(count for name, count in by_name.items() if "cpp_fused" in name)
    total = sum(by_name.values())
    assert kernels > 0, "the graphs' kernels are counted"
    assert total <= COMPILED_BUDGET, (f"{total} operators and kernels per compiled step, budget {COMPILED_BUDGET}; "
                                      f"by stage {dict(by_stage.most_common())}; most {by_name.most_common(12)}")
    waiting = {name: count for name, count in by_name.items()
               if name in ("aten::nonzero", "aten::item", "aten::_local_scalar_dense", "aten::unique", "aten::_unique2",
                           "aten::masked_select")}
    assert not waiting, f"host waits in a compiled step: {waiting}"
