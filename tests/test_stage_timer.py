"""The stage timer: the host's clock on the CPU, and on CUDA timing events read without waiting,
driven here by fake events (a fake device whose work completes when the test says so)."""

from __future__ import annotations

from dataclasses import dataclass, field

import pytest

from ogmapping.config import resolve
from ogmapping.mapper import Mapper
from ogmapping.quality.evaluation import open_frames
from ogmapping.runtime.stage_timer import StageTimer


@dataclass
class FakeDevice:
    """A device clock in milliseconds and the point up to which its queued work has run."""

    now_ms: float = 0.0
    recorded: int = 0
    completed: int = 0  # events recorded before this sequence number have completed
    waits: int = 0  # blocking synchronisations
    events: list[FakeEvent] = field(default_factory=list)

    def event(self) -> FakeEvent:
        event = FakeEvent(self)
        self.events.append(event)
        return event

    def finish(self) -> None:
        self.completed = self.recorded


@dataclass(eq=False)
class FakeEvent:
    device: FakeDevice
    sequence: int = -1
    at_ms: float = 0.0

    def record(self) -> None:
        self.sequence, self.at_ms = self.device.recorded, self.device.now_ms
        self.device.recorded += 1

    def query(self) -> bool:
        return 0 <= self.sequence < self.device.completed

    def synchronize(self) -> None:
        self.device.waits += 1
        self.device.completed = max(self.device.completed, self.sequence + 1)

    def elapsed_time(self, end: FakeEvent) -> float:
        assert self.query() and end.query(), "read before both events completed"
        return end.at_ms - self.at_ms


def timed(timer: StageTimer, device: FakeDevice, name: str, ms: float) -> None:
    with timer.stage(name):
        device.now_ms += ms


def test_the_host_path_sums_the_clock_per_stage() -> None:
    ticks = iter([0.0, 0.5, 1.0, 1.25, 2.0, 3.0])
    timer = StageTimer(clock=lambda: next(ticks))
    for name in ("decode", "loss", "decode"):
        with timer.stage(name):
            pass
    assert timer.totals() == {"decode": 1.5, "loss": 0.25}


def test_device_pairs_stay_pending_until_their_end_completes() -> None:
    device = FakeDevice()
    timer = StageTimer(device.event)
    timed(timer, device, "decode", 2.0)
    timed(timer, device, "loss", 3.0)
    assert timer.pending == 2 and device.waits == 0
    device.completed = 2  # decode's pair has run, loss's has not
    timed(timer, device, "backward", 4.0)  # its start reads what has completed, without waiting
    assert timer.pending == 2 and device.waits == 0
    device.finish()
    timed(timer, device, "decode", 1.0)
    assert timer.pending == 1 and device.waits == 0


def test_reading_the_totals_waits_for_every_pending_pair() -> None:
    device = FakeDevice()
    timer = StageTimer(device.event)
    for name, ms in (("decode", 2.0), ("loss", 3.0), ("decode", 0.5)):
        timed(timer, device, name, ms)
    assert device.waits == 0
    assert timer.totals() == pytest.approx({"decode": 2.5e-3, "loss": 3e-3})
    assert timer.pending == 0 and device.waits == 3


def test_pending_pairs_are_bounded_and_events_reused() -> None:
    device = FakeDevice()
    timer = StageTimer(device.event, max_pending=4)
    for _ in range(10):
        timed(timer, device, "step", 1.0)
    assert timer.pending == 4 and device.waits == 6  # the oldest, read by waiting for it
    device.finish()
    for _ in range(10):
        timed(timer, device, "step", 1.0)
        device.finish()
    assert device.waits == 6 and len(device.events) <= 2 * 4 + 2
    assert timer.totals() == pytest.approx({"step": 20e-3})


def test_a_stage_that_raises_is_not_counted_and_returns_its_event() -> None:
    device = FakeDevice()
    timer = StageTimer(device.event)
    with pytest.raises(RuntimeError), timer.stage("decode"):
        raise RuntimeError("boom")
    timed(timer, device, "loss", 1.0)
    assert len(device.events) == 2
    assert timer.totals() == pytest.approx({"loss": 1e-3})


def test_a_cpu_mapper_times_its_stages_on_the_host() -> None:
    frames = open_frames("synthetic", "synthetic", "0:2", scale=0.25)
    mapper = Mapper(resolve("sparse", overrides={"keyframes.first_iterations": "2"}), "cpu")
    assert mapper.timer.pending == 0
    for position in frames.selection.streamed:
        mapper.process(frames.load(position))
    timings = mapper.stats().timings
    assert {"preprocess", "allocate", "keyframes", "decode", "rasterize", "loss", "backward"} <= set(timings)
    assert all(seconds > 0 for seconds in timings.values())
    assert mapper.timings == timings
