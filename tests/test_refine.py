"""Progressive refinement rules (paper 3.2) and pruning, on hand-built maps."""

import dataclasses
import math

import torch

from ogmapping.config import RefineConfig
from ogmapping.model.gaussians import GaussianSet
from ogmapping.optim.refine import Proposals, accumulate, propose, propose_error, refine
from ogmapping.runtime.host_read import read, reads
from ogmapping.structure.anchors import AnchorMap
from ogmapping.structure.octree import PAD, SparseVoxelOctree

VOXEL = 0.4
CONFIG = RefineConfig(grad_threshold=1.0, min_observations=1, max_new_anchors=100)


def build_map(positions: list[list[float]], levels: list[int], n_offsets: int = 2):
    octree = SparseVoxelOctree(VOXEL, max_level=2)
    anchors = AnchorMap(n_offsets, 4, with_features=True, device=torch.device("cpu"))
    points = torch.tensor(positions)
    level_tensor = torch.tensor(levels)
    codes = torch.zeros(len(levels), dtype=torch.int64)
    centers = torch.zeros(len(levels), 3)
    for level in range(3):
        mask = level_tensor == level
        if mask.any():
            codes[mask] = octree.codes_of(points[mask], level)
            octree.insert(codes[mask], level)
            centers[mask] = octree.centers(codes[mask], level)
    sizes = VOXEL / torch.pow(4.0, level_tensor.float())
    anchors.add(codes, level_tensor, centers, sizes, torch.randn(len(levels), 4), None)
    return anchors, octree


def proposed(anchors: AnchorMap, octree: SparseVoxelOctree, config: RefineConfig = CONFIG) -> Proposals:
    """The proposals of anchor-based growth, their counts read."""
    proposals = propose(anchors, octree, config)
    return proposals.settled([int(count) for count in read(proposals.counts)])


def grow(anchors: AnchorMap, octree: SparseVoxelOctree, config: RefineConfig, voxel: float, optimizer) -> int:
    return refine(anchors, octree, config, voxel, optimizer).grown


def prune(anchors: AnchorMap, config: RefineConfig, optimizer) -> int:
    no_growth = dataclasses.replace(config, growth="none")
    return refine(anchors, SparseVoxelOctree(VOXEL, 2), no_growth, VOXEL, optimizer).pruned


def set_gradient(anchors: AnchorMap, row: int, slot: int, value: float) -> None:
    anchors.grad_sum[row, slot] = value
    anchors.grad_count[row, slot] = 1


def test_gradient_below_threshold_grows_nothing():
    anchors, octree = build_map([[0.1, 0.1, 0.1]], [0])
    set_gradient(anchors, 0, 0, 0.99)
    assert proposed(anchors, octree).codes.numel() == 0


def test_occupied_cell_promotes_to_the_next_level():
    anchors, octree = build_map([[0.1, 0.1, 0.1]], [0])
    set_gradient(anchors, 0, 0, 1.5)  # offset 0: the Gaussian sits in its own (occupied) level-0 cell
    added = grow(anchors, octree, CONFIG, VOXEL, None)
    assert added == 1
    assert anchors.levels.tolist() == [0, 1]
    assert math.isclose(float(torch.exp(anchors.log_scales.detach()[1, 0])), VOXEL / 4, rel_tol=1e-6)
    assert bool(octree.contains(octree.codes_of(anchors.positions[1:2], 1), 1).all())


def test_free_cell_gets_an_anchor_of_the_same_level():
    anchors, octree = build_map([[0.1, 0.1, 0.1]], [0])
    with torch.no_grad():
        anchors.offsets[0, 1] = torch.tensor([1.5, 0.0, 0.0])  # moves the Gaussian one coarse cell over
    set_gradient(anchors, 0, 1, 5.0)
    grow(anchors, octree, CONFIG, VOXEL, None)
    assert anchors.levels.tolist() == [0, 0]
    assert octree.count(0) == 2


def test_threshold_doubles_per_level():
    anchors, octree = build_map([[0.1, 0.1, 0.1], [1.01, 1.01, 1.01]], [0, 1])
    set_gradient(anchors, 1, 0, 1.5)  # above tau_0 but below tau_1 = 2 tau_0
    assert proposed(anchors, octree).codes.numel() == 0
    set_gradient(anchors, 1, 0, 2.5)
    proposals = proposed(anchors, octree)
    assert proposals.levels.tolist() == [2]


def test_a_gaussian_grows_at_most_once():
    anchors, octree = build_map([[0.1, 0.1, 0.1]], [0])
    set_gradient(anchors, 0, 0, 3.0)
    assert grow(anchors, octree, CONFIG, VOXEL, None) == 1
    anchors.reset_statistics()
    set_gradient(anchors, 0, 0, 3.0)
    with torch.no_grad():
        anchors.offsets[0, 0] = torch.tensor([0.3, 0.3, 0.3])  # even in a fresh cell it may not spawn again
    assert grow(anchors, octree, CONFIG, VOXEL, None) == 0
    set_gradient(anchors, 0, 1, 3.0)  # its sibling still can
    assert grow(anchors, octree, CONFIG, VOXEL, None) == 1


def test_finest_level_never_promotes_past_max_level():
    anchors, octree = build_map([[0.01, 0.01, 0.01]], [2])
    set_gradient(anchors, 0, 0, 100.0)
    assert proposed(anchors, octree).codes.numel() == 0


def test_duplicate_proposals_become_one_anchor():
    anchors, octree = build_map([[0.1, 0.1, 0.1]], [0])
    set_gradient(anchors, 0, 0, 3.0)
    set_gradient(anchors, 0, 1, 3.0)  # both offsets are 0: the same level-1 cell
    assert grow(anchors, octree, CONFIG, VOXEL, None) == 1


def test_prune_removes_faint_anchors_and_optimizer_state_follows():
    anchors, _ = build_map([[0.1, 0.1, 0.1], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0]], [0, 0, 0])
    offsets = anchors.parameter("offsets")
    optimizer = torch.optim.Adam([offsets, anchors.parameter("features"), anchors.parameter("log_scales")], lr=0.1)
    weights = torch.arange(1.0, 4.0).view(3, 1, 1)  # each anchor's moments its own
    ((anchors.offsets * weights).sum() + anchors.features.sum() + anchors.log_scales.sum()).backward()
    optimizer.step()
    moments = optimizer.state[offsets]["exp_avg"].clone()
    anchors.observations[:] = torch.tensor([20, 20, 2])
    anchors.max_opacity[:] = torch.tensor([0.5, 0.001, 0.001])  # the third is faint but seen too rarely
    removed = prune(anchors, RefineConfig(prune_opacity=0.01, prune_min_observations=10), optimizer)
    assert removed == 1 and len(anchors) == 2
    # compacted in place: the same buffer, its moments following their anchors, the freed row inert
    assert optimizer.param_groups[0]["params"][0] is anchors.parameter("offsets") is offsets
    state = optimizer.state[offsets]["exp_avg"]
    assert state.shape == offsets.shape == (anchors.capacity, 2, 3)
    assert torch.equal(state[:2], moments[[0, 2]]) and not state[2:].any()
    assert not anchors.live[2:].any() and anchors.live[:2].all()


def test_prune_keeps_anchors_that_were_not_rendered_in_the_interval():
    anchors, _ = build_map([[0.1, 0.1, 0.1], [1.0, 1.0, 1.0]], [0, 0])
    anchors.observations[:] = torch.tensor([20, 20])
    anchors.max_opacity[0] = 0.001  # rendered this interval, and faint
    # the second anchor was in no window view since the last step: no opacity on record
    assert prune(anchors, RefineConfig(prune_opacity=0.01, prune_min_observations=10), None) == 1
    assert len(anchors) == 1 and torch.allclose(anchors.positions[0], torch.tensor([1.0, 1.0, 1.0]))


# ``refine.growth``: Scaffold-GS's error-based growth and no growth, against the same hand-built maps.
ERROR = RefineConfig(grad_threshold=1.0, min_observations=1, max_new_anchors=100, growth="error")


def test_error_growth_proposes_at_every_level_the_gradient_reaches():
    anchors, octree = build_map([[0.1, 0.1, 0.1]], [0])
    with torch.no_grad():
        anchors.offsets[0, 1] = torch.tensor([1.5, 0.0, 0.0])  # one coarse cell over: a free level-0 cell
    set_gradient(anchors, 0, 0, 5.0)  # reaches tau_0, 2 tau_0 and 4 tau_0; its own level-0 cell is taken
    set_gradient(anchors, 0, 1, 2.5)  # reaches tau_0 and 2 tau_0
    proposals = propose_error(anchors, octree, ERROR)
    assert sorted(proposals.levels.tolist()) == [0, 1, 1, 2]
    assert proposals.parents.tolist() == [0, 0, 0, 0]
    assert grow(anchors, octree, ERROR, VOXEL, None) == 4
    assert [octree.count(level) for level in range(3)] == [2, 2, 1]


def test_error_growth_ignores_the_anchor_level_and_may_go_coarser():
    anchors, octree = build_map([[0.01, 0.01, 0.01]], [2])
    set_gradient(anchors, 0, 0, 1.5)  # over tau_0 only: the anchor-based rule would need 4 tau_0 here
    proposals = propose_error(anchors, octree, ERROR)
    assert proposals.levels.tolist() == [0]
    assert proposed(anchors, octree).codes.numel() == 0


def test_error_growth_spawns_again_in_a_later_interval():
    anchors, octree = build_map([[0.1, 0.1, 0.1]], [0])
    set_gradient(anchors, 0, 0, 2.5)  # reaches levels 0 and 1; its level-0 cell is taken
    assert grow(anchors, octree, ERROR, VOXEL, None) == 1  # its level-1 cell
    assert not bool(anchors.spawned.any())
    anchors.reset_statistics()
    set_gradient(anchors, 0, 0, 2.5)
    with torch.no_grad():
        anchors.offsets[0, 0] = torch.tensor([0.3, 0.3, 0.3])  # now in a free level-1 cell
    assert grow(anchors, octree, ERROR, VOXEL, None) == 1


def test_no_growth_grows_nothing():
    anchors, octree = build_map([[0.1, 0.1, 0.1]], [0])
    set_gradient(anchors, 0, 0, 100.0)
    none = RefineConfig(grad_threshold=1.0, min_observations=1, growth="none")
    assert grow(anchors, octree, none, VOXEL, None) == 0
    assert len(anchors) == 1 and [octree.count(level) for level in range(3)] == [1, 0, 0]


def test_accumulate_adds_the_scaled_gradient_norms_of_visible_gaussians_only():
    anchors, _ = build_map([[0.1, 0.1, 0.1], [1.1, 0.1, 0.1]], [0, 0])
    zeros = torch.zeros(4, 3)
    gaussians = GaussianSet(means=zeros, quats=torch.zeros(4, 4), scales=zeros, opacities=torch.full((4,), 0.5),
                            colors=zeros, rows=torch.tensor([0, 0, 1, 1]), slots=torch.tensor([0, 1, 0, 1]),
                            anchor_rows=torch.tensor([0, 1]), anchor_opacity=torch.tensor([0.5, 0.5]))
    grad = torch.tensor([[1.0, 0.0], [0.0, 2.0], [float("nan"), 5.0], [3.0, 4.0]])
    visible = torch.tensor([True, True, False, True])
    accumulate(anchors, gaussians, grad, visible, width=4, height=2)  # pixels -> NDC: x * 2, y * 1
    torch.testing.assert_close(anchors.grad_sum, torch.tensor([[2.0, 2.0], [0.0, math.hypot(6.0, 4.0)]]))
    assert anchors.grad_count.tolist() == [[1, 1], [0, 1]]
    assert anchors.observations.tolist() == [1, 1]


def test_proposals_are_padded_to_a_fixed_size_and_counted_on_the_device():
    anchors, octree = build_map([[0.1, 0.1, 0.1], [1.0, 1.0, 1.0]], [0, 0])
    set_gradient(anchors, 0, 0, 3.0)  # promoted to level 1
    set_gradient(anchors, 1, 0, 3.0)
    set_gradient(anchors, 1, 1, 3.0)  # the same level-1 cell as its sibling: one anchor
    proposals = propose(anchors, octree, CONFIG)
    assert proposals.codes.numel() == 4, "every Gaussian of the map is a slot: the size never depends on the data"
    assert proposals.counts.tolist() == [0, 2, 0]
    assert proposals.levels.tolist() == [1, 1, 3, 3] and proposals.codes[2:].tolist() == [PAD, PAD]
    assert proposals.parents[:2].sort().values.tolist() == [0, 1]


def test_the_strongest_proposals_win_when_there_are_more_than_the_limit():
    anchors, octree = build_map([[0.1, 0.1, 0.1], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0]], [0, 0, 0])
    for row, value in enumerate((2.0, 5.0, 3.0)):
        set_gradient(anchors, row, 0, value)
    proposals = proposed(anchors, octree, dataclasses.replace(CONFIG, max_new_anchors=2))
    assert sorted(proposals.parents.tolist()) == [1, 2]
    assert anchors.spawned[:, 0].tolist() == [False, True, True]


def test_a_refinement_reads_the_device_once():
    anchors, octree = build_map([[0.1, 0.1, 0.1], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0]], [0, 0, 0])
    set_gradient(anchors, 0, 0, 3.0)
    anchors.observations[:] = 20
    anchors.max_opacity[:] = torch.tensor([0.5, 0.001, 0.5])
    before = reads()
    config = dataclasses.replace(CONFIG, prune_opacity=0.01, prune_min_observations=10)
    refined = refine(anchors, octree, config, VOXEL, None)
    assert reads() - before == 1
    assert (refined.grown, refined.pruned) == (1, 1) and len(anchors) == 3
    assert anchors.levels.tolist() == [0, 0, 1], "the faint anchor went, the grown one came after the others"
