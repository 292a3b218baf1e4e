"""The budget for a realtime session's skipped frames, on a clock the test turns."""

from __future__ import annotations

from ogserver.recording.skipped_budget import SkippedBudget


class Clock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def test_the_rate_refills_one_seconds_worth_at_most() -> None:
    clock = Clock()
    budget = SkippedBudget(total=10_000, per_second=300, clock=clock)
    assert [budget.take(100) for _ in range(4)] == [True, True, True, False]
    clock.now = 0.5  # 150 bytes back
    assert [budget.take(100) for _ in range(2)] == [True, False]
    clock.now = 100.0  # idle for long: still one second's worth
    assert [budget.take(100) for _ in range(4)] == [True, True, True, False]


def test_the_total_is_never_exceeded_and_zero_records_nothing() -> None:
    clock = Clock()
    budget = SkippedBudget(total=250, per_second=1000, clock=clock)
    assert [budget.take(100) for _ in range(3)] == [True, True, False]
    clock.now = 10.0
    assert not budget.take(100) and budget.take(50) and not budget.take(1)
    assert not SkippedBudget(total=0, per_second=1000).take(1)
    assert not SkippedBudget(total=1000, per_second=0).take(1)
