"""Steps by resolution: the multiple of the configured step counts a frame gets."""

from __future__ import annotations

import pytest

from ogmapping.config import KeyframeConfig, resolve
from ogmapping.frames.camera import Intrinsics
from ogmapping.optim.step_budget import step_multiple


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
    assert multiple * mapper._iterations_for(True) == 2 * config.keyframes.first_iterations
