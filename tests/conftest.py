"""Shared test fixtures: where the real data lives, and small mapper configs."""

import os
from pathlib import Path

import pytest

import ogmapping  # noqa: F401 (first, so its OpenMP settings precede torch in any test module)

# isort: split
import torch

# Without a GPU the Triton kernels run interpreted on CPU tensors. Triton reads this when it defines a
# kernel, its own library's included, so it is set before anything in the session imports triton
# (torch.compile's Inductor does, whatever the device).
if not torch.cuda.is_available():
    os.environ.setdefault("TRITON_INTERPRET", "1")

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


@pytest.fixture
def tiny_snapshot(tmp_path: Path) -> Path:
    """A snapshot of two tiny synthetic frames mapped with two and one iterations: a real map in seconds."""
    from ogmapping.config import resolve
    from ogmapping.datasets.synthetic import SyntheticSource
    from ogmapping.mapper import Mapper

    source = SyntheticSource(n_frames=2, width=64, height=48)
    mapper = Mapper(resolve("sparse", overrides={"keyframes.first_iterations": 2, "keyframes.iterations": 1}), "cpu")
    for position in range(len(source)):
        mapper.process(source[position])
    path = tmp_path / "map.safetensors"
    path.write_bytes(mapper.snapshot())
    return path
