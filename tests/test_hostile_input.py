"""What one frame, config or snapshot can cost the engine is bounded before the work starts."""

from __future__ import annotations

import dataclasses
import json
import threading
import time
import tracemalloc

import numpy as np
import pytest
import torch
from safetensors.torch import save as save_tensors

from ogmapping.config import ConfigBounds, OctreeConfig, resolve
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.preprocess import reproject_depth
from ogmapping.mapper import Mapper
from ogmapping.persist import snapshot
from ogmapping.runtime.time_budget import Budget, Stop
from ogmapping.structure import extent

SMALL = {"keyframes.first_iterations": 2, "keyframes.iterations": 1, "keyframes.frame_iterations": 1}


@pytest.fixture(scope="module")
def source() -> SyntheticSource:
    return SyntheticSource(n_frames=6, width=64, height=48)


def test_registration_memory_does_not_grow_with_the_footprint() -> None:
    """A depth pixel almost touching the colour camera once spread over ~200x200 colour pixels (GBs for a
    small frame); and a colour camera 30x denser than its depth camera grew memory with the square of 30."""
    depth_k = Intrinsics(100.0, 100.0, 80.0, 60.0, 160, 120)
    near = np.eye(4)
    near[2, 3] = -1.96  # the colour camera sits 1.96 m in front of the depth camera: depth 2 m lands at 4 cm
    for color_k, transform in ((depth_k, near), (Intrinsics(3000.0, 3000.0, 160.0, 120.0, 320, 240), None)):
        tracemalloc.start()
        start = time.perf_counter()
        registered = reproject_depth(np.full((120, 160), 2.0, np.float32), depth_k, color_k, transform)
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        assert registered.shape == (color_k.height, color_k.width) and registered.max() > 0
        assert peak < 128 << 20, f"registration peaked at {peak >> 20} MiB"
        assert time.perf_counter() - start < 10


def test_a_snapshot_config_beyond_the_bounds_is_refused_before_any_tensor(source: SyntheticSource) -> None:
    """A 216 KB snapshot naming model.hash_log2_size=24 once made the server allocate 2 GiB."""
    mapper = Mapper(resolve("dense", overrides=SMALL))
    state = mapper.state()
    config = state.config.to_dict()
    config["model"]["hash_log2_size"] = 24
    metadata = snapshot.read_metadata(mapper.snapshot())
    crafted = save_tensors({"anchors.codes": state.tensors["anchors.codes"]},
                           metadata={**metadata, "config": json.dumps(config)})
    with pytest.raises(ValueError, match=r"config_bounds\.max_hash_table_mib"):
        Mapper.restore(crafted, bounds=ConfigBounds())
    Mapper.restore(mapper.snapshot(), bounds=ConfigBounds())  # the map's own config is within them


def test_a_frame_stops_at_its_deadline_and_when_cancelled(source: SyntheticSource) -> None:
    Mapper(resolve("sparse-fast", overrides=SMALL)).process(source[0])  # compiled kernels loaded: not timed below
    mapper = Mapper(resolve("sparse-fast", overrides={**SMALL, "keyframes.first_iterations": 500}))
    result = mapper.process(source[0], Budget(seconds=1.0))
    assert result.stopped is Stop.DEADLINE and 0 < result.iterations < 500 and result.seconds < 10
    assert mapper.model.iterations == result.iterations, "what the frame learnt stays in the map"
    cancelled = Budget(cancelled=threading.Event())
    cancelled.cancelled.set()
    result = mapper.process(source[1], cancelled)
    assert result.stopped is Stop.CANCELLED and result.iterations == 0
    assert mapper.process(source[2]).stopped is None


def test_a_one_row_frame_does_not_poison_the_map(source: SyntheticSource) -> None:
    """A 100000x1 frame entered the keyframe set; its half-size copy for the window had no rows, and
    later frames that drew it failed."""
    mapper = Mapper(resolve("sparse-fast", overrides={**SMALL, "keyframes.global_count": 3}))
    mapper.process(source[0])
    wide = Intrinsics(50.0, 50.0, 5000.0, 0.5, 10000, 1)
    mapper.process(dataclasses.replace(source[1], rgb=np.full((1, 10000, 3), 0.5, np.float32),
                                       depth=np.full((1, 10000), 2.0, np.float32),
                                       color_intrinsics=wide, depth_intrinsics=wide))
    assert wide.scaled(0.5).height == 1
    for position in range(2, len(source)):
        mapper.process(source[position])


def test_gaussians_carried_out_of_range_grow_nothing(source: SyntheticSource) -> None:
    """A client's optim.offsets_lr = 38695 threw Gaussians kilometres away; growth from them failed every frame."""
    growing = {"refine.interval": 1, "refine.min_observations": 0, "refine.grad_threshold": 0.0}
    mapper = Mapper(resolve("sparse-fast", overrides={**SMALL, **growing}))
    mapper.process(source[0])
    with torch.no_grad():
        mapper.model.anchors.offsets.fill_(1e9)
    mapper.model.anchors.spawned.fill_(False)  # every thrown Gaussian a growth candidate again
    mapper.process(source[1])
    thrown = mapper.model.anchors.offsets.abs().amax(dim=-1) > 1e8
    assert thrown.any() and not mapper.model.anchors.spawned[thrown].any(), "a Gaussian out of range proposed an anchor"


def test_the_map_reaches_as_far_as_its_finest_cells_allow() -> None:
    octree = OctreeConfig()  # 0.1 m cells, max_level 2: 2^20 cells of 6.25 mm = 6.5 km
    camera = Intrinsics(50.0, 50.0, 40.0, 30.0, 80, 60)
    assert 5000 < extent.map_radius(octree) < 6554
    pose = np.eye(4)
    pose[0, 3] = 6000.0
    assert extent.frame_radius(pose, camera, octree.depth_max) > extent.map_radius(octree)
    pose[0, 3] = 5000.0
    assert extent.frame_radius(pose, camera, octree.depth_max) < extent.map_radius(octree)
    assert extent.map_radius(dataclasses.replace(octree, voxel_size=0.2)) == 2 * extent.map_radius(octree)
