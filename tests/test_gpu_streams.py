"""Mappers on CUDA each run on a stream of their own: two mapping side by side, from two threads,
make the maps each makes alone, and device tensors handed from one mapper to another arrive whole."""

from __future__ import annotations

import threading

import numpy as np
import pytest
import torch

from ogmapping.config import resolve
from ogmapping.mapper import Mapper
from ogmapping.quality.evaluation import open_frames
from ogmapping.queries import Rendered

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")]
FRAMES = 8
# CUDA maps are not bit-for-bit repeatable (gradients of Gaussians sharing a pixel are summed with
# atomic adds in varying order, docs/cuda.md), so renders are compared within a tolerance.
COLOUR_TOLERANCE = 0.02  # mean absolute difference


def frames():
    return open_frames("synthetic", "synthetic", f"0:{FRAMES}", n_frames=FRAMES, width=160, height=120)


def mapped(start: threading.Barrier | None = None) -> Mapper:
    source = frames()
    mapper = Mapper(resolve("sparse"), "cuda")
    if start is not None:
        start.wait()
    for position in source.selection.streamed:
        mapper.process(source.load(position))
    return mapper


def rendered(mapper: Mapper) -> Rendered:
    frame = frames().load(FRAMES // 2)
    return mapper.render(frame.c2w, frame.color_intrinsics)


def test_two_mappers_on_two_threads_make_the_maps_each_makes_alone() -> None:
    alone = rendered(mapped())
    start = threading.Barrier(2)
    results: dict[int, Mapper] = {}
    errors: list[BaseException] = []

    def run(slot: int) -> None:
        try:
            results[slot] = mapped(start)
        except BaseException as error:  # reported below, not lost in the thread
            errors.append(error)

    threads = [threading.Thread(target=run, args=(slot,)) for slot in range(2)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not errors, errors
    default = torch.cuda.default_stream()
    assert results[0].stream != default and results[1].stream != default
    assert results[0].stream != results[1].stream
    for mapper in results.values():
        side_by_side = rendered(mapper)
        assert np.abs(side_by_side.color - alone.color).mean() < COLOUR_TOLERANCE
        assert np.abs(side_by_side.alpha - alone.alpha).mean() < COLOUR_TOLERANCE


def test_a_state_on_the_device_moves_whole_between_mappers() -> None:
    source = mapped()
    state = source.state(training_state=True)
    assert any(tensor.is_cuda for tensor in state.tensors.values())
    copy = Mapper.from_state(state, "cuda", training_state=True)
    del state
    assert copy.stream != source.stream
    mine, theirs = rendered(source), rendered(copy)
    np.testing.assert_allclose(theirs.color, mine.color, atol=1e-5)
    np.testing.assert_allclose(theirs.depth, mine.depth, atol=1e-4)
    decoded = source.decode_at(np.zeros(3))
    assert len(decoded) > 0 and bool(torch.isfinite(decoded.means).all())
