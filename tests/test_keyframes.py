"""Keyframe insertion by overlap and the dynamic window's draws."""

import random

import torch

from ogmapping.config import KeyframeConfig
from ogmapping.frames.camera import Intrinsics
from ogmapping.optim.keyframes import Keyframe, KeyframeSet
from ogmapping.runtime.host_read import read
from ogmapping.structure.footprint import Footprint, overlap

INTRINSICS = Intrinsics(10, 10, 4, 3, 8, 6)


def keyframe(index: int, codes: list[int]) -> Keyframe:
    return Keyframe.capture(index, torch.zeros(6, 8, 3), torch.zeros(6, 8), INTRINSICS, torch.eye(4),
                            footprint(codes))


def footprint(codes: list[int]) -> Footprint:
    return Footprint.of_codes(torch.tensor(sorted(set(codes)), dtype=torch.int64))


def inserts(frames: KeyframeSet, codes: list[int], index: int = 1) -> bool:
    """Whether frame ``index`` seeing ``codes`` becomes a keyframe."""
    return frames.inserts(read(frames.overlap_with_last(footprint(codes)))[0], index)


def test_overlap_ratio_matches_set_arithmetic():
    generator = torch.Generator().manual_seed(0)
    for _ in range(20):
        a = set(torch.randint(0, 50, (30,), generator=generator).tolist())
        b = set(torch.randint(0, 50, (30,), generator=generator).tolist())
        expected = len(a & b) / len(a | b)
        got = float(overlap(footprint(list(a)), footprint(list(b))))
        assert abs(got - expected) < 1e-12
        keys = torch.tensor(sorted(a | b | {60, 61}))  # the same keys: compared by masks alone
        on_keys = float(overlap(Footprint(keys, torch.isin(keys, torch.tensor(sorted(a)))),
                                Footprint(keys, torch.isin(keys, torch.tensor(sorted(b))))))
        assert on_keys == got


def test_overlap_of_empty_footprints():
    assert float(overlap(footprint([]), footprint([]))) == 1.0
    assert float(overlap(footprint([1]), footprint([]))) == 0.0


def test_insertion_follows_the_threshold():
    frames = KeyframeSet(KeyframeConfig(overlap_threshold=0.5))
    assert inserts(frames, [1, 2, 3])
    frames.insert(keyframe(0, [1, 2, 3, 4]))
    assert not inserts(frames, [1, 2, 3, 4, 5])  # 4/5 overlap
    assert inserts(frames, [3, 4, 5, 6, 7])  # 2/7 overlap


def test_a_frame_max_gap_frames_after_the_last_keyframe_is_one_whatever_its_overlap():
    frames = KeyframeSet(KeyframeConfig(overlap_threshold=0.5, max_gap=10))
    assert inserts(frames, [1, 2, 3], index=4)
    frames.insert(keyframe(4, [1, 2, 3, 4]))
    assert not inserts(frames, [1, 2, 3, 4], index=13)
    assert inserts(frames, [1, 2, 3, 4], index=14)
    plain = KeyframeSet(KeyframeConfig(overlap_threshold=0.5))
    plain.insert(keyframe(4, [1, 2, 3, 4]))
    assert not inserts(plain, [1, 2, 3, 4], index=10**6)  # 0: overlap alone


def test_local_and_global_split_by_overlap_weight():
    frames = KeyframeSet(KeyframeConfig(local_threshold=0.5))
    frames.insert(keyframe(0, list(range(10))))  # overlaps K_new by 8/12
    frames.insert(keyframe(1, list(range(100, 110))))  # no overlap
    frames.insert(keyframe(2, list(range(2, 12))))
    assert frames.local == [0]
    assert frames.global_ == [1]


def test_window_draws_without_replacement_and_changes_between_iterations():
    config = KeyframeConfig(local_threshold=0.2, local_count=3, global_count=2)
    frames = KeyframeSet(config, seed=1)
    for index in range(8):
        frames.insert(keyframe(index, list(range(0, 20)) if index % 2 == 0 else list(range(100 + index, 120))))
    frames.insert(keyframe(99, list(range(0, 20))))
    assert len(frames.local) >= 3 and len(frames.global_) >= 2
    draws = []
    for _ in range(20):
        indices = [kf.index for kf in frames.draw_window(view_is_newest=True)]
        assert 99 not in indices, "K_new is the view, not drawn beside it"
        assert len(indices) == 3 + 2
        assert len(set(indices)) == len(indices), "no keyframe twice in one window"
        local = {frames.keyframes[i].index for i in frames.local}
        assert sum(i in local for i in indices) == 3
        draws.append(tuple(indices))
    assert len(set(draws)) > 1, "the window is drawn afresh every iteration"


def stalest_set(global_count: int) -> KeyframeSet:
    """One local keyframe and six global ones beside K_new, drawn by ``stalest``."""
    frames = KeyframeSet(KeyframeConfig(local_threshold=0.5, local_count=1, global_count=global_count,
                                        global_draw="stalest"), seed=3)
    frames.insert(keyframe(0, list(range(0, 20))))
    for index in range(1, 7):
        frames.insert(keyframe(index, list(range(100 * index, 100 * index + 20))))
    frames.insert(keyframe(7, list(range(0, 20))))
    assert frames.local == [0] and frames.global_ == [1, 2, 3, 4, 5, 6]
    return frames


def test_the_stalest_draw_revisits_every_global_keyframe_in_turn():
    frames = stalest_set(global_count=2)
    for _ in range(3):  # two rounds over the six global keyframes, each keyframe once a round
        seen = []
        for _ in range(3):
            drawn = [kf.index for kf in frames.draw_window(view_is_newest=True)]
            assert drawn[0] == 0 and len(drawn) == 3
            seen += drawn[1:]
        assert sorted(seen) == [1, 2, 3, 4, 5, 6]
    assert frames.draws == 9 and frames.trained[0] == 9


def test_the_stalest_draw_breaks_ties_at_random():
    orders = set()
    for seed in (11, 12, 13):
        frames = stalest_set(global_count=6)
        frames.random.seed(seed)
        drawn = [kf.index for kf in frames.draw_window(view_is_newest=True)[1:]]
        assert sorted(drawn) == [1, 2, 3, 4, 5, 6]  # all tied (never trained): every one, in a drawn order
        orders.add(tuple(drawn))
    assert len(orders) > 1


def test_the_random_draw_is_the_papers_uniform_draw():
    """``random`` (the default) draws b1 local then b2 global keyframes with ``random.sample``, as it always has."""
    config = KeyframeConfig(local_threshold=0.5, local_count=1, global_count=2)
    frames = KeyframeSet(config, seed=5)
    frames.insert(keyframe(0, list(range(0, 20))))
    for index in range(1, 7):
        frames.insert(keyframe(index, list(range(100 * index, 100 * index + 20))))
    frames.insert(keyframe(7, list(range(0, 20))))
    expected = random.Random(5)
    for _ in range(5):
        drawn = [kf.index for kf in frames.draw_window(view_is_newest=True)]
        assert drawn == expected.sample([0], 1) + expected.sample([1, 2, 3, 4, 5, 6], 2)


def test_window_with_few_keyframes_uses_what_exists():
    frames = KeyframeSet(KeyframeConfig(local_count=2, global_count=2))
    frames.insert(keyframe(0, [1, 2]))
    assert frames.draw_window(view_is_newest=True) == []


def test_keyframes_are_stored_compact_and_drawn_as_float_views():
    generator = torch.Generator().manual_seed(2)
    rgb = torch.randint(0, 256, (6, 8, 3), generator=generator).float() / 255.0  # an 8-bit image
    depth = 1.0 + 3.0 * torch.rand(6, 8, generator=generator)
    stored = Keyframe.capture(4, rgb, depth, INTRINSICS, torch.eye(4), torch.tensor([1, 2]))
    assert stored.rgb.dtype == torch.uint8 and stored.depth.dtype == torch.float16
    view = stored.view(torch.device("cpu"), compiled=True)
    assert torch.equal(view.rgb, rgb), "8-bit colour comes back exactly"
    assert view.depth.dtype == torch.float32 and float((view.depth - depth).abs().max()) <= 2e-3  # float16 at 4 m
    assert view.ssim_reference.mean.shape == (6, 8, 3)


def test_downscaled_keyframe_matches_a_resized_camera():
    generator = torch.Generator().manual_seed(1)
    rgb = torch.rand(6, 8, 3, generator=generator)
    depth = 1.0 + torch.rand(6, 8, generator=generator)
    depth[0, 0] = 0.0
    original = Keyframe.capture(3, rgb, depth, INTRINSICS, torch.eye(4), torch.tensor([1, 2]))
    half = original.downscaled(0.5)
    assert half.intrinsics == INTRINSICS.scaled(0.5)
    assert half.rgb.shape == (3, 4, 3) and half.depth.shape == (3, 4)
    stored = original.rgb.float() / 255.0
    area = stored.reshape(3, 2, 4, 2, 3).mean(dim=(1, 3))
    assert float((half.rgb.float() / 255.0 - area).abs().max()) <= 0.5 / 255.0 + 1e-6  # area average, rounded
    assert set(half.depth.flatten().tolist()) <= set(original.depth.flatten().tolist())  # measured values only
    assert half.index == 3 and half.footprint is original.footprint
    assert original.downscaled(0.5) is half and original.downscaled(1.0) is original


def test_window_scale_stops_at_the_minimum_width():
    from ogmapping.config import resolve
    from ogmapping.mapper import Mapper

    mapper = Mapper(resolve("sparse", overrides={"keyframes.window_scale": 0.5, "keyframes.window_min_width": 160}))
    assert mapper.steps.window_scale(640) == 0.5
    assert mapper.steps.window_scale(320) == 0.5
    assert mapper.steps.window_scale(240) == 160 / 240
    assert mapper.steps.window_scale(160) == 1.0
    assert mapper.steps.window_scale(80) == 1.0


def test_a_frame_between_keyframes_draws_the_newest_keyframe_as_local():
    frames = KeyframeSet(KeyframeConfig(local_count=1, global_count=0))
    frames.insert(keyframe(0, [1, 2]))
    assert [kf.index for kf in frames.draw_window(view_is_newest=False)] == [0]


def test_footprints_are_refreshed_on_the_current_map():
    """With a footprint function, the newest keyframe is compared as it sees the map now."""
    seen = {0: [1, 2, 3, 4]}
    frames = KeyframeSet(KeyframeConfig(overlap_threshold=0.8), footprint=lambda kf: footprint(seen[kf.index]))
    frames.insert(keyframe(0, [1, 2]))
    assert not inserts(frames, [1, 2, 3, 4]), "cells allocated later count for the keyframe too"
    assert frames.keyframes[0].footprint.codes().tolist() == [1, 2, 3, 4]


# Fixed windows (``keyframes.window``): chosen once per inserted keyframe, the same at every draw.
def fixed_set(window: str, local: int = 1, global_: int = 2) -> KeyframeSet:
    return KeyframeSet(KeyframeConfig(window=window, local_count=local, global_count=global_), seed=3)


def test_fixed_windows_stay_fixed_between_insertions():
    for window in ("random", "overlap", "coverage"):
        frames = fixed_set(window)
        for index in range(6):
            frames.insert(keyframe(index, list(range(10 * index, 10 * index + 15))))
        draws = {tuple(kf.index for kf in frames.draw_window(view_is_newest=True)) for _ in range(10)}
        assert len(draws) == 1, window
        (indices,) = draws
        assert 5 not in indices and len(indices) == 3 and len(set(indices)) == 3, window
        assert tuple(kf.index for kf in frames.draw_window(view_is_newest=False)) == indices, window


def test_random_window_is_redrawn_only_when_a_keyframe_arrives():
    frames = fixed_set("random", local=1, global_=1)
    chosen = set()
    for index in range(12):
        frames.insert(keyframe(index, [index]))
        chosen.add(tuple(frames.fixed))
        assert len(set(frames.fixed)) == min(2, index) and all(p < index for p in frames.fixed)
    assert len(chosen) > 3


def test_overlap_window_picks_the_most_overlapping_keyframes():
    frames = fixed_set("overlap", local=1, global_=1)
    frames.insert(keyframe(0, list(range(0, 10))))  # overlap with K_new (cells 3..12): 7/13
    frames.insert(keyframe(1, list(range(100, 110))))  # 0
    frames.insert(keyframe(2, list(range(3, 13))))  # 1
    frames.insert(keyframe(3, list(range(8, 18))))  # 5/15
    frames.insert(keyframe(4, list(range(5, 15))))  # 8/12
    frames.insert(keyframe(9, list(range(3, 13))))
    assert frames.fixed == [2, 4]


def test_coverage_window_picks_greedily():
    frames = fixed_set("coverage", local=2, global_=1)
    frames.insert(keyframe(0, list(range(0, 15))))  # adds 5 cells K_new does not see
    frames.insert(keyframe(1, list(range(20, 29))))  # adds 9
    frames.insert(keyframe(2, [*range(20, 26), 30, 31]))  # adds 8 alone, only 2 after keyframe 1
    frames.insert(keyframe(3, list(range(40, 44))))  # adds 4
    frames.insert(keyframe(9, list(range(0, 10))))
    # Most new cells alone would be 1, 2, 0; greedily, keyframe 2 adds little once 1 is in.
    assert [frames.keyframes[p].index for p in frames.fixed] == [1, 0, 3]


def test_local_keyframes_are_told_apart_from_global_ones():
    frames = KeyframeSet(KeyframeConfig(local_threshold=0.5))
    frames.insert(keyframe(0, [1, 2, 3]))
    frames.insert(keyframe(1, [50, 51]))
    frames.insert(keyframe(2, [1, 2, 3, 4]))
    assert frames.is_local(frames.keyframes[0]), "overlaps K_new"
    assert not frames.is_local(frames.keyframes[1]), "sees none of what K_new sees"
    assert frames.is_local(frames.keyframes[2]), "the newest keyframe itself"


def test_window_size_is_what_a_draw_returns():
    config = KeyframeConfig(local_threshold=0.5, local_count=1, global_count=2)
    frames = KeyframeSet(config, seed=4)
    frames.insert(keyframe(0, [1, 2]))
    sizes = [(frames.window_size(True), frames.window_size(False))]
    for index, codes in enumerate(([100, 101], [200, 201], [1, 2]), start=1):
        frames.insert(keyframe(index, codes))
        sizes.append((frames.window_size(True), frames.window_size(False)))
        for newest in (True, False):
            assert frames.window_size(newest) == len(frames.draw_window(newest))
    assert sizes == [(0, 1), (1, 2), (2, 3), (3, 3)]
    fixed = fixed_set("random")
    for index in range(4):
        fixed.insert(keyframe(index, [index]))
    assert fixed.window_size(False) == len(fixed.draw_window(False)) == 3


def test_frame_renders_caps_a_streamed_frames_steps_as_the_window_fills():
    from ogmapping.config import resolve
    from ogmapping.mapper import Mapper

    overrides = {"keyframes.frame_iterations": 3, "keyframes.frame_renders": 4, "keyframes.global_count": 2,
                 "keyframes.local_threshold": 0.5}
    mapper = Mapper(resolve("sparse", overrides=overrides))
    assert mapper.iterations_for(is_keyframe=False) == 0, "nothing to train before the first keyframe"
    mapper.keyframes.insert(keyframe(0, [1, 2]))
    assert mapper.iterations_for(is_keyframe=False) == 2, "view + newest keyframe: 2 renders a step"
    mapper.keyframes.insert(keyframe(1, [100, 101]))
    mapper.keyframes.insert(keyframe(2, [200, 201]))
    assert mapper.iterations_for(is_keyframe=False) == 1, "view + newest + two global: 4 renders a step"
    mapper.config.keyframes.frame_renders = 1
    assert mapper.iterations_for(is_keyframe=False) == 1, "never below one step"
    mapper.config.keyframes.frame_renders = 0
    assert mapper.iterations_for(is_keyframe=False) == 3, "0: frame_iterations as it is"


def test_loss_view_weighs_the_view_once_the_window_is_full():
    from ogmapping.config import resolve
    from ogmapping.mapper import Mapper

    overrides = {"keyframes.local_threshold": 0.5, "keyframes.global_count": 2, "loss.view": 0.5}
    mapper = Mapper(resolve("sparse", overrides=overrides))
    mapper.keyframes.footprint = None  # compare the codes given here, not footprints on the (empty) map
    mapper.keyframes.insert(keyframe(0, [1, 2]))
    mapper.keyframes.insert(keyframe(1, [100, 101]))
    assert not mapper.keyframes.is_full(), "one global keyframe of two"
    assert mapper.steps.window_weights(mapper.keyframes.draw_window(True)) == [1.0, 1.0]
    mapper.keyframes.insert(keyframe(2, [200, 201]))
    assert mapper.keyframes.is_full()
    assert mapper.steps.window_weights(mapper.keyframes.draw_window(False)) == [0.5, 1.0, 1.0, 1.0]
    assert mapper.steps.window_weights([]) == [0.5], "the view alone (a window that draws nothing)"


def test_a_keyframe_captured_on_the_cpu_is_on_the_host_at_once():
    stored = keyframe(3, [1, 2])
    assert stored.ready is None and stored.rgb is stored.host_rgb and stored.depth is stored.host_depth
    assert stored.rgb.dtype == torch.uint8 and stored.depth.dtype == torch.float16
    assert torch.equal(stored.device_depth(torch.device("cpu")), stored.depth.float())
