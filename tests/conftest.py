"""Shared test fixtures: where the real data lives, and small mapper configs."""

from pathlib import Path

import pytest

import ogmapping  # noqa: F401 (first, so its OpenMP settings precede torch in any test module)

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SEVEN_SCENES = SHARED_DATA / "7scenes-redkitchen"


@pytest.fixture
def seven_scenes() -> Path:
    if not SEVEN_SCENES.exists():
        pytest.skip(f"real data not found at {SEVEN_SCENES} (CI has ../shared beside the checkout)")
    return SEVEN_SCENES
