"""Pose corrections: a corrected keyframe's anchors move by its rigid delta, nothing else moves, the keyframe
takes the corrected pose and joins the next windows; bad corrections change nothing; snapshots keep them."""

import numpy as np
import pytest
import torch

from ogmapping.config import resolve
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.frames.rotation import axis_angle_matrix
from ogmapping.mapper import Mapper
from ogmapping.mapping.corrections import delta, jump
from ogmapping.optim.keyframes import REVISIT_DRAWS


def mapped(step: str = "dynamic") -> tuple[Mapper, SyntheticSource]:
    source = SyntheticSource(n_frames=6, width=64, height=48)
    config = resolve("sparse", overrides={"keyframes.iterations": 2, "keyframes.first_iterations": 4,
                                          "keyframes.frame_iterations": 1, "refine.interval": 3,
                                          "refine.min_observations": 1, "step": step,
                                          "keyframes.overlap_threshold": 0.95})
    mapper = Mapper(config)
    for position in range(len(source)):
        mapper.process(source[position])
    return mapper, source


def turned(c2w: np.ndarray, degrees: float = 5.0, shift: tuple = (0.05, -0.02, 0.03)) -> np.ndarray:
    """``c2w`` turned about the world z axis and shifted: a rigid correction."""
    motion = np.eye(4)
    motion[:3, :3] = axis_angle_matrix(np.array([0.0, 0.0, 1.0]), np.radians(degrees))
    motion[:3, 3] = shift
    return motion @ c2w


@pytest.fixture(scope="module", params=["dynamic", "static"])
def session(request):
    return mapped(request.param)


def gaussian_means(mapper: Mapper) -> torch.Tensor:
    anchors = mapper.model.anchors
    return (anchors.positions.unsqueeze(1) + anchors.offsets.detach() * torch.exp(anchors.log_scales.detach())
            .unsqueeze(1)).double()


def test_jump_measures_metres_and_degrees():
    metres, degrees = jump(np.eye(4), turned(np.eye(4), 30.0, (3.0, 4.0, 0.0)))
    assert metres == pytest.approx(5.0) and degrees == pytest.approx(30.0)


def test_a_correction_moves_exactly_its_keyframes_anchors(session):
    mapper, _ = session
    anchors = mapper.model.anchors
    assert len(mapper.keyframes) >= 2
    owners = anchors.keyframe.clone()
    assert bool((owners >= 0).all()), "every anchor belongs to a keyframe"
    target = 1
    mine = owners == target
    assert bool(mine.any()) and bool((~mine).any())
    old = mapper.keyframes.keyframes[target].c2w.double().numpy().copy()
    corrected = turned(old)
    before_positions = anchors.positions.clone().double()
    before_means = gaussian_means(mapper)
    others = [keyframe.c2w.clone() for position, keyframe in enumerate(mapper.keyframes.keyframes)
              if position != target]
    moved = mapper.correct_poses({target: corrected})
    assert moved.keyframes == 1 and moved.anchors == int(mine.sum())
    motion = torch.as_tensor(delta(old, corrected))
    expected = before_positions[mine] @ motion[:3, :3].T + motion[:3, 3]
    assert torch.allclose(anchors.positions.double()[mine], expected, atol=1e-5)
    assert torch.equal(anchors.positions.double()[~mine], before_positions[~mine])
    # Every Gaussian of a moved anchor moves with it (offsets turned), the others stay.
    means = gaussian_means(mapper)
    moved_means = before_means[mine] @ motion[:3, :3].T + motion[:3, 3]
    assert torch.allclose(means[mine], moved_means, atol=1e-4)
    assert torch.equal(means[~mine], before_means[~mine])
    # Re-coded at their new cells, which the octree holds.
    octree = mapper.model.octree
    for level in range(octree.levels):
        at = anchors.levels == level
        assert torch.equal(anchors.codes[at], octree.codes_of(anchors.positions[at], level))
        assert bool(octree.contains(anchors.codes[at], level).all())
    assert np.allclose(mapper.keyframes.keyframes[target].c2w.double().numpy(), corrected, atol=1e-6)
    rest = [keyframe.c2w for position, keyframe in enumerate(mapper.keyframes.keyframes) if position != target]
    assert all(torch.equal(a, b) for a, b in zip(others, rest, strict=True))
    assert list(mapper.keyframes.revisits) == [(target, REVISIT_DRAWS)]


def test_corrected_keyframes_join_the_window_then_leave():
    mapper, source = mapped()
    mapper.correct_poses({0: turned(mapper.keyframes.keyframes[0].c2w.double().numpy(), 1.0, (0.01, 0, 0))})
    draws = [mapper.keyframes.draw_window(view_is_newest=False) for _ in range(REVISIT_DRAWS + 1)]
    first = mapper.keyframes.keyframes[0]
    assert all(any(keyframe is first for keyframe in window) for window in draws[:REVISIT_DRAWS])
    assert not mapper.keyframes.revisits
    result = mapper.process(source[0])  # mapping goes on
    assert np.isfinite(result.loss)


def test_bad_corrections_change_nothing():
    mapper, _ = mapped()
    state = {name: value.clone() for name, value in mapper.state().tensors.items()}
    good = mapper.keyframes.keyframes[0].c2w.double().numpy()
    bad = good.copy()
    bad[:3, :3] *= 1.5
    with pytest.raises(ValueError, match="keyframe 1: the corrected pose rotation is not orthonormal"):
        mapper.correct_poses({0: turned(good), 1: bad})
    with pytest.raises(ValueError, match="keyframe 99"):
        mapper.correct_poses({0: turned(good), 99: good})
    far = good.copy()
    far[:3, 3] = 1e12
    with pytest.raises(ValueError, match="beyond the range"):
        mapper.correct_poses({0: far})
    after = mapper.state().tensors
    assert all(torch.equal(state[name], after[name]) for name in state)
    assert not mapper.keyframes.revisits


def test_snapshot_and_checkpoint_keep_corrected_positions(session):
    mapper, source = session
    mapper.correct_poses({0: turned(mapper.keyframes.keyframes[0].c2w.double().numpy(), 2.0, (0.0, 0.03, 0.0))})
    anchors = mapper.model.anchors
    restored = Mapper.restore(mapper.snapshot())
    assert torch.equal(restored.model.anchors.positions, anchors.positions)
    # A snapshot holds no keyframes: its anchors belong to none of the keyframes a restored map makes.
    assert bool((restored.model.anchors.keyframe == -1).all()) and not len(restored.keyframes)
    resumed = Mapper.from_state(mapper.state(training_state=True), training_state=True)
    assert torch.equal(resumed.model.anchors.keyframe, anchors.keyframe)
    assert torch.equal(resumed.model.anchors.positions, anchors.positions)
    assert list(resumed.keyframes.revisits) == list(mapper.keyframes.revisits)
    for mine, theirs in zip(mapper.keyframes.keyframes, resumed.keyframes.keyframes, strict=True):
        assert torch.equal(mine.c2w, theirs.c2w)
    frame = source[2]
    assert np.array_equal(mapper.render(frame.c2w, frame.color_intrinsics).color,
                          resumed.render(frame.c2w, frame.color_intrinsics).color)


def test_old_snapshots_without_positions_or_keyframes_load():
    mapper, _ = mapped()
    state = mapper.state()
    for name in ("anchors.positions", "anchors.keyframe"):
        del state.tensors[name]
    restored = Mapper.from_state(state)
    anchors = restored.model.anchors
    assert bool((anchors.keyframe == -1).all())
    assert torch.equal(anchors.positions, restored.model.octree.centers_by_level(anchors.codes, anchors.levels))
