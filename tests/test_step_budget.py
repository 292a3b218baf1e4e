"""Steps by resolution: the multiple of the configured step counts a frame gets."""

from __future__ import annotations

import pytest
import torch

from ogmapping.config import KeyframeConfig, resolve
from ogmapping.frames.camera import Intrinsics
from ogmapping.optim.step_budget import step_count_multiple, step_multiple
from ogmapping.quality.evaluation import open_frames


def camera(width: int, height: int) -> Intrinsics:
    return Intrinsics(fx=width, fy=width, cx=width / 2, cy=height / 2, width=width, height=height)


@pytest.mark.parametrize(("width", "height", "multiple"), [
    (160, 120, 1), (320, 240, 1), (600, 340, 1), (640, 480, 1),  # every size the presets were tuned at
    (1200, 680, 2), (1280, 720, 2), (1920, 1080, 3),
])
def test_the_multiple_follows_the_linear_size(width: int, height: int, multiple: int) -> None:
    assert step_multiple(KeyframeConfig(), camera(width, height)) == multiple


def test_a_zero_reference_never_scales() -> None:
    assert step_multiple(KeyframeConfig(steps_reference_pixels=0), camera(1920, 1080)) == 1


def test_a_mapper_at_1200x680_takes_twice_the_configured_steps() -> None:
    from ogmapping.mapper import Mapper

    config = resolve("sparse")
    mapper = Mapper(config, "cpu")
    multiple = step_multiple(config.keyframes, camera(1200, 680))
    assert multiple * mapper.iterations_for(True) == 2 * config.keyframes.first_iterations


@pytest.mark.parametrize(("width", "height", "linear", "area"), [
    (320, 240, 1, 1), (600, 340, 1, 1), (640, 480, 1, 1), (1200, 680, 2, 4), (1920, 1080, 3, 9),
])
def test_area_growth_squares_the_multiple_of_the_step_counts(width: int, height: int, linear: int, area: int) -> None:
    size = camera(width, height)
    assert step_count_multiple(KeyframeConfig(), size) == linear
    assert step_count_multiple(KeyframeConfig(steps_growth="area"), size) == area
    assert step_multiple(KeyframeConfig(steps_growth="area"), size) == linear  # what the other switches take


@pytest.mark.parametrize(("growth", "steps"), [("linear", 6), ("area", 12)])
def test_a_mapper_takes_the_grown_step_count_on_a_finer_frame(growth: str, steps: int) -> None:
    from ogmapping.mapper import Mapper

    # 80x60 against a reference of 1200 pixels: a linear multiple of sqrt(4) = 2.
    config = resolve("sparse-fast", overrides={"keyframes.first_iterations": "3", "keyframes.steps_growth": growth,
                                               "keyframes.steps_reference_pixels": "1200"})
    frame = open_frames("synthetic", "synthetic", "0:1", 1, 0.25, n_frames=40).load(0)
    assert Mapper(config, "cpu").process(frame).iterations == steps


def test_area_growth_maps_as_the_doubled_counts_set_by_hand() -> None:
    from ogmapping.mapper import Mapper

    frames = open_frames("synthetic", "synthetic", "0:2", 1, 0.25, n_frames=40)
    base = {"keyframes.steps_reference_pixels": "1200", "keyframes.frame_iterations": "1"}  # 80x60: x2
    states = []
    for overrides in ({"keyframes.steps_growth": "area", "keyframes.first_iterations": "3"},
                      {"keyframes.steps_growth": "linear", "keyframes.first_iterations": "6",
                       "keyframes.frame_iterations": "2"}):
        mapper = Mapper(resolve("sparse-fast", overrides={**base, **overrides}), "cpu")
        for position in (0, 1):
            mapper.process(frames.load(position))
        states.append(mapper.state().tensors)
    assert states[0].keys() == states[1].keys()
    assert all(torch.equal(value, states[1][name]) for name, value in states[0].items())
