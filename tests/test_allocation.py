"""Map densification strategies (``octree.allocation``): octree, naive unique, projection."""

import pytest
import torch

from ogmapping.config import OctreeConfig, resolve
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.frames.camera import Intrinsics
from ogmapping.frames.geometry import backproject
from ogmapping.mapper import Mapper
from ogmapping.render.output import RenderOutput
from ogmapping.structure.allocation import allocate, projection_allocation, unexplained_pixels
from ogmapping.structure.extent import check_frame
from ogmapping.structure.octree import PAD, SparseVoxelOctree

VOXEL = 0.1
# 8 x 4 pixels looking down +z; at depth 1 a pixel spans 0.1 m (one coarse cell).
INTRINSICS = Intrinsics(10.0, 10.0, 4.0, 2.0, 8, 4)
POSE = torch.eye(4)


def render_of(alpha: torch.Tensor, depth: torch.Tensor):
    def render() -> RenderOutput:
        empty = torch.zeros(0, 2)
        return RenderOutput(torch.zeros(*alpha.shape, 3), depth, alpha, empty, torch.zeros(0, dtype=torch.bool))
    return render


def test_unique_allocation_gives_the_octree_allocation():
    generator = torch.Generator().manual_seed(3)
    fast, naive, unread = SparseVoxelOctree(VOXEL, 2), SparseVoxelOctree(VOXEL, 2), SparseVoxelOctree(VOXEL, 2)
    for step in range(6):
        depth = 0.5 + torch.rand(4, 8, generator=generator) * (1 + step)
        depth[0, step % 8] = 0.0
        pose = torch.eye(4)
        pose[:3, 3] = torch.rand(3, generator=generator) * 0.3 * step
        expected = allocate("octree", fast, depth, INTRINSICS, pose).settle(fast)
        got = allocate("unique", naive, depth, INTRINSICS, pose).settle(naive)
        assert torch.equal(got, expected) and torch.equal(naive.keys(0), fast.keys(0))
        at_fixed_sizes = allocate("octree", unread, depth, INTRINSICS, pose, unread=True).settle(unread)
        assert torch.equal(at_fixed_sizes, expected) and torch.equal(unread.keys(0), fast.keys(0))


def test_unique_and_octree_mappers_build_the_same_map():
    source = SyntheticSource(n_frames=2, width=24, height=18)
    settings = {"keyframes.iterations": 1, "keyframes.first_iterations": 1}
    maps = [Mapper(resolve("sparse", overrides={**settings, "octree.allocation": kind}))
            for kind in ("octree", "unique")]
    for mapper in maps:
        for position in range(len(source)):
            mapper.process(source[position])
    assert torch.equal(maps[0].model.anchors.codes, maps[1].model.anchors.codes)
    assert torch.equal(maps[0].model.anchors.offsets, maps[1].model.anchors.offsets)


def test_projection_on_an_empty_map_allocates_every_observed_cell():
    depth = torch.ones(4, 8)
    octree = SparseVoxelOctree(VOXEL, 2)
    expected = allocate("octree", octree, depth, INTRINSICS, POSE).settle(octree)
    never = render_of(torch.zeros(4, 8), torch.zeros(4, 8))
    assert torch.equal(projection_allocation(SparseVoxelOctree(VOXEL, 2), depth, INTRINSICS, POSE, never), expected)


def test_projection_adds_where_the_map_is_empty_and_duplicates_at_edges():
    depth = torch.ones(4, 8)
    octree = SparseVoxelOctree(VOXEL, 2)
    left = depth.clone()
    left[:, 4:] = 0
    mapped = allocate("octree", octree, left, INTRINSICS, POSE).settle(octree)  # the map covers the left half
    alpha = torch.ones(4, 8)
    alpha[:, 4:] = 0.0  # ...and renders nothing on the right
    alpha[:, 3] = 0.3  # its edge column renders faint
    rendered_depth = torch.where(alpha > 0, depth, torch.zeros_like(depth))
    added = projection_allocation(octree, depth, INTRINSICS, POSE, render_of(alpha, rendered_depth))
    right = depth.clone()
    right[:, :3] = 0  # the edge column and the empty half
    expected = octree.observed(backproject(right, INTRINSICS, POSE))
    assert torch.equal(added, expected)
    duplicated = added[torch.isin(added, mapped)]
    assert duplicated.numel() == 4, "the faint edge column gets anchors again where cells hold one"
    assert torch.equal(octree.keys(0), torch.unique(torch.cat([mapped, added])))


def test_projection_depth_rule_catches_surfaces_in_front_of_the_map():
    depth = torch.ones(4, 8)
    depth[0, 0] = 0.0  # unmeasured: never selected
    rendered = depth + 1e-3  # a slight disagreement everywhere sets the median error
    rendered[1, 1] = 1.04  # behind, but by less than 50x the median
    rendered[2, 2] = 3.0  # the map's surface lies far behind this measurement: something new in front
    rendered[3, 6] = 0.2  # rendered in front of the measurement: not the depth rule's case
    output = render_of(torch.ones(4, 8), rendered)()
    mask = unexplained_pixels(depth, output)
    assert mask.nonzero().tolist() == [[2, 2]]


def test_mapper_runs_every_switch_off_the_defaults():
    source = SyntheticSource(n_frames=2, width=24, height=18)
    overrides = {"keyframes.iterations": 1, "keyframes.first_iterations": 1, "refine.interval": 1,
                 "refine.min_observations": 1, "refine.grad_threshold": 1e-9, "keyframes.overlap_threshold": 1.0,
                 "octree.allocation": "projection", "refine.growth": "error", "keyframes.window": "coverage"}
    mapper = Mapper(resolve("sparse", overrides=overrides))
    results = [mapper.process(source[position]) for position in range(len(source))]
    assert all(result.keyframe for result in results)
    assert len(mapper.model.anchors) >= mapper.model.octree.count(0) > 0
    assert max(mapper.model.anchors.level_counts(2)[1:]) > 0, "error-based growth added finer anchors"


def test_octree_allocation_waits_for_nothing_until_settled():
    """The new cells and the octree's keys keep a size the frame alone sets (padded with PAD) until the
    host reads the count; settling trims both to what a checked insert gives."""
    depth = torch.ones(4, 8)
    depth[:, 6:] = 0.0
    padded, checked = SparseVoxelOctree(VOXEL, 2), SparseVoxelOctree(VOXEL, 2)
    checked.insert(checked.observed(backproject(depth, INTRINSICS, POSE)))
    cells = allocate("octree", padded, depth, INTRINSICS, POSE, unread=True)
    assert cells.padded.numel() == 32 and padded.keys(0).numel() == 32
    assert (cells.padded[cells.count:] == PAD).all()
    assert torch.equal(cells.settle(padded), checked.keys(0)) and torch.equal(padded.keys(0), checked.keys(0))
    again = allocate("octree", padded, torch.ones(4, 8), INTRINSICS, POSE, unread=True)  # two new columns
    assert int(again.count) == 8 and padded.keys(0).numel() == 24 + 32
    assert torch.equal(padded.keys(0)[-24:], torch.full((24,), PAD))
    again.settle(padded)
    assert padded.count(0) == 32


def test_a_frame_beyond_the_octree_range_is_refused_before_allocation():
    settings = OctreeConfig(voxel_size=VOXEL, max_level=2, depth_max=5.0)
    far = torch.eye(4).numpy()
    far[0, 3] = 2e4  # 20 km out: past the finest cells' Morton range at 0.1 m and level 2
    with pytest.raises(ValueError, match="the map reaches"):
        check_frame(far, INTRINSICS, settings)
    check_frame(torch.eye(4).numpy(), INTRINSICS, settings)
