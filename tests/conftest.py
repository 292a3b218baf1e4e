"""Shared test fixtures: where the real data lives, and small mapper configs."""

from pathlib import Path

import pytest

import ogmapping  # noqa: F401 (first, so its OpenMP settings precede torch in any test module)

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SEVEN_SCENES = SHARED_DATA / "7scenes-redkitchen"
REPLICA_ROOM0 = SHARED_DATA / "replica-room0" / "data"


@pytest.fixture
def seven_scenes() -> Path:
    if not SEVEN_SCENES.exists():
        pytest.skip(f"real data not found at {SEVEN_SCENES} (CI has ../shared beside the checkout)")
    return SEVEN_SCENES


@pytest.fixture(scope="session")
def seven_scenes_if_present() -> Path | None:
    """7-Scenes where ../shared lies beside the checkout, else None (for tests that then use synthetic frames)."""
    return SEVEN_SCENES if SEVEN_SCENES.exists() else None


@pytest.fixture
def replica_room0() -> Path:
    if not REPLICA_ROOM0.exists():
        pytest.skip(f"Replica room0 frames not found at {REPLICA_ROOM0} (CI has ../shared beside the checkout)")
    return REPLICA_ROOM0
