"""The anchor map's rows live in buffers with a capacity: growth writes rows, pruning compacts them in
place, and only a doubling of the capacity reallocates, carrying every value and Adam's moments."""

from __future__ import annotations

import pytest
import torch

from ogmapping.structure.anchors import LEARNABLE, AnchorMap


def grown(anchors: AnchorMap, count: int, start: int = 0, optimizer: torch.optim.Optimizer | None = None) -> None:
    codes = torch.arange(start, start + count)
    anchors.add(codes, torch.zeros(count, dtype=torch.int64), codes.view(-1, 1).expand(count, 3).float(),
                torch.full((count,), 0.5), torch.ones(count, 4), optimizer)


def test_growth_writes_rows_until_the_capacity_doubles() -> None:
    anchors = AnchorMap(2, 4, True, torch.device("cpu"), capacity=4)
    buffers = {name: anchors.buffer(name) for name in ("positions", *LEARNABLE)}
    grown(anchors, 3)
    assert len(anchors) == 3 and anchors.capacity == 4
    assert all(anchors.buffer(name) is buffer for name, buffer in buffers.items()), "rows written in place"
    assert anchors.live.tolist() == [True, True, True, False]
    optimizer = torch.optim.Adam([anchors.parameter(name) for name in LEARNABLE], lr=0.1)
    (anchors.offsets.sum() + anchors.log_scales.sum() + anchors.features.sum()).backward()
    optimizer.step()
    moments = optimizer.state[anchors.parameter("offsets")]["exp_avg"][:3].clone()
    grown(anchors, 2, start=3, optimizer=optimizer)  # 5 rows: twice the capacity
    assert anchors.capacity == 8 and len(anchors) == 5 and anchors.live.sum() == 5
    offsets = anchors.parameter("offsets")
    assert optimizer.param_groups[0]["params"][1] is offsets, "the optimiser steps the new buffer"
    state = optimizer.state[offsets]["exp_avg"]
    assert state.shape == offsets.shape == (8, 2, 3)
    assert torch.equal(state[:3], moments) and not state[3:].any(), "moments carried, new rows' zero"
    assert anchors.positions[:, 0].tolist() == [0, 1, 2, 3, 4] and not anchors.buffer("positions")[5:].any()
    grown(anchors, 20, start=5, optimizer=optimizer)  # more than a doubling: exactly what is needed
    assert anchors.capacity == 25 and len(anchors) == 25


def test_rows_past_the_count_are_inert_after_pruning() -> None:
    anchors = AnchorMap(2, 4, True, torch.device("cpu"), capacity=8)
    grown(anchors, 5)
    with torch.no_grad():
        anchors.offsets.fill_(1.0)
    anchors.max_opacity[:] = 0.5
    anchors.keep(torch.tensor([True, False, True, False, True]), None, 3)
    assert len(anchors) == 3 and anchors.positions[:, 0].tolist() == [0, 2, 4]
    assert not anchors.buffer("offsets")[3:].any() and anchors.buffer("max_opacity")[3:].eq(-torch.inf).all()
    assert not anchors.live[3:].any()


def test_assigning_live_rows_checks_their_shape() -> None:
    anchors = AnchorMap(2, 4, True, torch.device("cpu"))
    grown(anchors, 3)
    anchors.observations = torch.tensor([4, 5, 6])
    assert anchors.buffer("observations")[:4].tolist() == [4, 5, 6, 0]
    with pytest.raises(ValueError, match=r"anchors\.observations: shape"):
        anchors.observations = torch.tensor([1, 2])
