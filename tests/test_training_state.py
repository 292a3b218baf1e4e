"""A mapper rebuilt from its state with the training state (a server's checkpoint) maps on bit for
bit as the original; from a plain snapshot's state it starts afresh, and ignores a training state."""

from __future__ import annotations

import numpy as np
import pytest

from ogmapping.config import resolve
from ogmapping.mapper import Mapper
from ogmapping.persist import snapshot
from ogmapping.quality.evaluation import open_frames

TINY = {"keyframes.first_iterations": "6", "keyframes.iterations": "2"}
SMALL_HASH = {"model.hash_log2_size": "12"}  # the default 2^19-row table costs a minute here, to no purpose


@pytest.mark.parametrize("preset", ["sparse-fast", "dense"])  # anchor features / hash grid and its lazy Adam
def test_a_mapper_rebuilt_with_its_training_state_maps_on_exactly(preset: str) -> None:
    frames = open_frames("synthetic", "synthetic", "0:6", 1, 0.25, n_frames=40)
    loaded = [frames.load(position) for position in range(6)]
    config = resolve(preset, overrides={**TINY, **(SMALL_HASH if preset == "dense" else {})})
    original = Mapper(config)
    for frame in loaded[:3]:
        original.process(frame)
    data = snapshot.encode(original.state(training_state=True), half=False)
    resumed = Mapper.from_state(snapshot.decode(data), training_state=True)
    fresh_start = Mapper.from_state(snapshot.decode(data))  # the map only: fresh keyframes and moments
    assert len(resumed.keyframes) == len(original.keyframes) and len(fresh_start.keyframes) == 0
    before, after = original.keyframes, resumed.keyframes
    assert (after.draws, after.trained) == (before.draws, before.trained) and before.draws > 0
    for frame in loaded[3:]:
        expected = original.process(frame)
        got = resumed.process(frame)
        assert (got.keyframe, got.anchors, got.iterations, got.loss) == \
            (expected.keyframe, expected.anchors, expected.iterations, expected.loss)
        fresh_start.process(frame)
    pose, camera = loaded[2].c2w, loaded[2].color_intrinsics
    reference = original.render(pose, camera)
    assert np.array_equal(resumed.render(pose, camera).color, reference.color)
    assert not np.array_equal(fresh_start.render(pose, camera).color, reference.color)


def test_frame_indices_up_to_the_protocols_uint64_survive_a_checkpoint() -> None:
    frames = open_frames("synthetic", "synthetic", "0:2", 1, 0.25, n_frames=40)
    original = Mapper(resolve("sparse-fast", overrides=TINY))
    for frame, index in zip((frames.load(0), frames.load(1)), (2**64 - 1, 2**63), strict=True):
        frame.index = index
        original.process(frame)
    data = snapshot.encode(original.state(training_state=True), half=False)
    resumed = Mapper.from_state(snapshot.decode(data), training_state=True)
    assert [k.index for k in resumed.keyframes.keyframes] == [k.index for k in original.keyframes.keyframes]
    assert resumed.keyframes.keyframes[0].index == 2**64 - 1
