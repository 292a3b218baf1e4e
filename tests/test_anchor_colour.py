"""Anchor colours (model.anchor_colour): on in dense and sparse, started at zero or at the cell mean, learned, kept."""

import numpy as np
import pytest
import torch

from ogmapping.config import resolve
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.frames.camera import Intrinsics
from ogmapping.mapper import Mapper
from ogmapping.persist.snapshot import decode, encode
from ogmapping.structure.anchor_colour import cell_colour_logits, with_anchor_colours
from ogmapping.structure.octree import SparseVoxelOctree

CAMERA = Intrinsics(fx=40.0, fy=40.0, cx=32.0, cy=24.0, width=64, height=48)


def _wall_in_two_colours() -> tuple[torch.Tensor, torch.Tensor]:
    """A flat wall 1 m in front of the camera: red on the left half of the image, blue on the right."""
    rgb = torch.zeros(48, 64, 3)
    rgb[:, :32, 0] = 0.8
    rgb[:, 32:, 2] = 0.6
    return rgb, torch.ones(48, 64)


def test_each_cell_starts_at_the_mean_colour_of_its_points():
    octree = SparseVoxelOctree(voxel_size=0.1, max_level=0)
    rgb, depth = _wall_in_two_colours()
    c2w = torch.eye(4)
    codes = octree.insert(octree.codes_of(torch.tensor([[-0.35, 0.0, 1.0], [0.35, 0.0, 1.0], [0.0, 0.0, 3.0]])))
    logits, seen = cell_colour_logits(octree, codes, rgb, depth, CAMERA, c2w)
    centres = octree.centers(codes)
    left, right, behind = (int(torch.argmin((centres - torch.tensor(point)).norm(dim=1)))
                           for point in ([-0.35, 0.0, 1.0], [0.35, 0.0, 1.0], [0.0, 0.0, 3.0]))
    assert seen[left] and seen[right]
    assert torch.allclose(torch.sigmoid(logits[left]), torch.tensor([0.8, 1 / 255, 1 / 255]), atol=1e-4)
    assert torch.allclose(torch.sigmoid(logits[right]), torch.tensor([1 / 255, 1 / 255, 0.6]), atol=1e-4)
    assert not seen[behind], "a cell behind the wall holds none of the frame's points"
    assert torch.equal(logits[behind], torch.zeros(3))


def test_anchor_colour_is_added_to_every_gaussian_of_its_anchor():
    decoder_logits = torch.zeros(2, 3 * 4)
    colours = torch.tensor([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0], [7.0, 8.0, 9.0]])
    out = with_anchor_colours(decoder_logits, colours, torch.tensor([2, 0]))
    assert out.view(2, 4, 3)[0].tolist() == [[7.0, 8.0, 9.0]] * 4
    assert out.view(2, 4, 3)[1].tolist() == [[1.0, 2.0, 3.0]] * 4


def _first_frame_only(preset: str, **overrides) -> tuple[Mapper, object]:
    source = SyntheticSource(n_frames=1, width=64, height=48)
    mapper = Mapper(resolve(preset, overrides={"keyframes.first_iterations": 0, "model.anchor_colour": True,
                                               **overrides}))
    mapper.process(source[0])
    return mapper, source[0]


def test_new_anchors_start_at_their_cells_mean_colour_before_any_step():
    """With the "cell" start, decoder and anchor colour together give each new anchor's Gaussians,
    on average over its n slots and seen from the allocating frame, the logit of its cell's mean colour."""
    for preset in ("sparse", "dense"):
        mapper, frame = _first_frame_only(preset, **{"model.anchor_colour_start": "cell"})
        anchors = mapper.model.anchors
        rows = torch.arange(len(anchors))
        c2w = torch.as_tensor(frame.c2w, dtype=torch.float32)
        to_camera = c2w[:3, 3] - anchors.positions
        distances = to_camera.norm(dim=-1, keepdim=True)
        with torch.no_grad():
            _, decoder, _ = mapper.model.decoders.logits(mapper.model.features(rows), to_camera / distances, distances)
            colour = with_anchor_colours(decoder, anchors.colours, rows).view(len(anchors), -1, 3).mean(1)
        target, seen = cell_colour_logits(mapper.model.octree, anchors.codes, torch.as_tensor(frame.rgb),
                                          torch.as_tensor(frame.depth), frame.color_intrinsics, c2w)
        assert int(seen.sum()) == len(anchors), "every new anchor's cell holds points of the frame"
        assert torch.allclose(colour, target, atol=1e-4), preset


def test_dense_and_sparse_start_new_anchors_at_the_decoders_colour_and_sparse_fast_has_none():
    assert not resolve("sparse-fast").model.anchor_colour
    for preset in ("dense", "sparse"):
        config = resolve(preset)
        assert config.model.anchor_colour and config.model.anchor_colour_start == "zero", preset
        mapper, _ = _first_frame_only(preset)
        assert torch.equal(mapper.model.anchors.colours.detach(), torch.zeros(len(mapper.model.anchors), 3)), preset


def test_switched_off_the_map_has_no_anchor_colours():
    source = SyntheticSource(n_frames=1, width=64, height=48)
    mapper = Mapper(resolve("sparse", overrides={"keyframes.first_iterations": 0, "model.anchor_colour": False}))
    mapper.process(source[0])
    assert mapper.model.anchors.colours.shape == (len(mapper.model.anchors), 0)
    assert "anchors.colours" not in mapper.state().tensors
    assert "colours" not in {group["name"] for group in mapper.model.optimizer.param_groups}


def test_an_unknown_start_is_refused_by_name():
    with pytest.raises(ValueError, match=r"model\.anchor_colour_start must be one of zero, cell"):
        resolve("sparse", overrides={"model.anchor_colour_start": "pixel"})


def test_colours_learn_and_survive_a_snapshot_and_old_snapshots_still_load():
    source = SyntheticSource(n_frames=2, width=64, height=48)
    mapper = Mapper(resolve("sparse", overrides={"keyframes.first_iterations": 6, "model.anchor_colour": True}))
    mapper.process(source[0])
    started = mapper.model.anchors.colours.detach().clone()
    mapper.process(source[1])
    assert not torch.equal(mapper.model.anchors.colours.detach()[: len(started)], started), "colours are optimised"
    restored = Mapper.restore(mapper.snapshot())
    with mapper.lock, mapper.model.average.applied():  # a snapshot holds the map that renders: the average
        assert torch.allclose(restored.model.anchors.colours, mapper.model.anchors.colours, atol=1e-2)
    state = decode(mapper.snapshot())
    del state.tensors["anchors.colours"]
    older = Mapper.restore(encode(state))
    assert torch.equal(older.model.anchors.colours, torch.zeros(len(mapper.model.anchors), 3))
    frame = source[1]
    assert np.isfinite(older.render(frame.c2w, frame.color_intrinsics).color).all()


def test_strided_intrinsics_see_each_kept_pixel_where_the_full_image_does():
    from ogmapping.frames.geometry import pixel_rays

    full = Intrinsics(fx=500.0, fy=480.0, cx=321.3, cy=239.7, width=640, height=480)
    for stride, start in ((2, 1), (3, 1), (4, 2)):
        strided = full.strided(stride, start)
        assert (strided.width, strided.height) == (len(range(start, 640, stride)), len(range(start, 480, stride)))
        assert torch.allclose(pixel_rays(strided), pixel_rays(full)[start::stride, start::stride], atol=1e-5)


def test_strided_colour_means_match_every_pixel_on_a_wall():
    octree = SparseVoxelOctree(voxel_size=0.1, max_level=0)
    rgb, depth = _wall_in_two_colours()
    codes = octree.insert(octree.codes_of(torch.tensor([[-0.35, 0.0, 1.0], [0.35, 0.0, 1.0]])))
    every, _ = cell_colour_logits(octree, codes, rgb, depth, CAMERA, torch.eye(4))
    strided, _ = cell_colour_logits(octree, codes, rgb, depth, CAMERA, torch.eye(4), stride=3)
    assert torch.allclose(every, strided, atol=1e-5)
