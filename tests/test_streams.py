"""The per-mapper CUDA stream helpers do nothing on the CPU (and never touch torch.cuda there)."""

from __future__ import annotations

import pytest
import torch

from ogmapping.config import resolve
from ogmapping.mapper import Mapper
from ogmapping.runtime import streams


def no_cuda(*args, **kwargs):
    raise AssertionError("a CPU path touched torch.cuda")


def test_the_stream_helpers_are_no_ops_on_the_cpu(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("Stream", "current_stream", "stream", "set_stream"):
        monkeypatch.setattr(torch.cuda, name, no_cuda)
    assert streams.session_stream(torch.device("cpu")) is None
    tensor = torch.ones(3)
    with streams.on_stream(None):
        tensor = tensor * 2
    streams.handed_in(None, [tensor])
    streams.handed_out(None, [tensor])
    assert tensor.tolist() == [2.0, 2.0, 2.0]


def test_a_cpu_mapper_has_no_stream(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in ("Stream", "current_stream", "stream", "set_stream"):
        monkeypatch.setattr(torch.cuda, name, no_cuda)
    mapper = Mapper(resolve("sparse"), "cpu")
    assert mapper.stream is None
    again = Mapper.from_state(mapper.state(training_state=True), "cpu", training_state=True)
    assert again.stream is None and again.stats().anchors == 0
