"""Keyframe insertion depends on the camera path, not on the image resolution (Replica room0).

Before the footprint was the set of visible cells on the current map, this path made 1 keyframe at
600x340 and 18 at 300x170 with 5 cm voxels.
"""

import pytest

from ogmapping.config import resolve
from ogmapping.datasets import open_dataset
from ogmapping.frames.preprocess import resize_frame
from ogmapping.mapper import Mapper

NO_OPTIMISATION = {"keyframes.first_iterations": 0, "keyframes.iterations": 0, "keyframes.frame_iterations": 0}


def keyframe_indices(source, scale: float, overrides: dict) -> list[int]:
    mapper = Mapper(resolve("sparse", overrides={**NO_OPTIMISATION, **overrides}))
    return [i for i in range(len(source)) if mapper.process(resize_frame(source[i], scale)).keyframe]


@pytest.mark.realdata
@pytest.mark.parametrize("voxel_size", [0.05, 0.1])
def test_same_keyframes_at_every_resolution(replica_room0, voxel_size):
    source = open_dataset(str(replica_room0))
    overrides = {"octree.voxel_size": voxel_size, "keyframes.overlap_threshold": 0.93}
    full = keyframe_indices(source, 0.5, overrides)
    assert len(full) >= 3, "the threshold should make several keyframes on this path"
    quarter = keyframe_indices(source, 0.25, overrides)
    # Overlaps agree to ~0.5% across scales, so a crossing of the threshold may move by one frame.
    assert len(quarter) == len(full)
    assert all(abs(a - b) <= 1 for a, b in zip(quarter, full, strict=True))
