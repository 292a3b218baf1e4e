"""A dataset found from its own folder or the folder above it (downloads unpack to scene/data/ or
scene/room0/), for ogmap and ogclient alike."""

from __future__ import annotations

from pathlib import Path

import pytest

from ogmapping.datasets import Replica, SevenScenes, find_dataset, open_dataset


def replica_layout(root: Path) -> Path:
    (root / "results").mkdir(parents=True)
    (root / "results" / "depth000000.png").touch()
    (root / "traj.txt").touch()
    return root


def sevenscenes_layout(root: Path) -> Path:
    root.mkdir(parents=True)
    (root / "frame-000000.depth.png").touch()
    return root


@pytest.mark.parametrize("below", ["data", "room0"])
def test_the_folder_above_a_layout_finds_it(tmp_path: Path, below: str) -> None:
    scene = replica_layout(tmp_path / "scene" / below)
    assert find_dataset(tmp_path / "scene") == ("replica", scene)
    assert find_dataset(scene) == ("replica", scene)
    assert find_dataset(tmp_path / "scene", "replica") == ("replica", scene)


def test_data_is_preferred_and_several_other_subfolders_are_refused(tmp_path: Path) -> None:
    data = sevenscenes_layout(tmp_path / "scene" / "data")
    replica_layout(tmp_path / "scene" / "other")
    assert find_dataset(tmp_path / "scene") == ("7scenes", data)
    replica_layout(tmp_path / "two" / "a")
    sevenscenes_layout(tmp_path / "two" / "b")
    with pytest.raises(ValueError, match=r"several datasets under .*two: a \(replica\), b \(7scenes\); pass the one"):
        find_dataset(tmp_path / "two")
    with pytest.raises(ValueError, match="no known dataset layout"):
        find_dataset(tmp_path)  # two levels down is not looked at


def test_the_shared_replica_opens_from_its_top_folder(replica_room0: Path) -> None:
    top, inner = open_dataset(str(replica_room0.parent)), open_dataset(str(replica_room0))
    assert isinstance(top, Replica) and len(top) == len(inner) > 0
    assert (top[0].c2w == inner[0].c2w).all()


def test_the_shared_7scenes_opens_from_its_top_folder(seven_scenes: Path) -> None:
    assert isinstance(open_dataset(str(seven_scenes)), SevenScenes)
    assert find_dataset(seven_scenes) == ("7scenes", seven_scenes / "data")
