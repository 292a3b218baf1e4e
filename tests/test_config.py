"""Presets and overrides."""

import dataclasses
import json
from pathlib import Path
from typing import get_args

import pytest

from ogmapping.backends import BACKENDS
from ogmapping.config import (
    PRESETS,
    Backend,
    ConfigBounds,
    Growth,
    MapperConfig,
    Window,
    load_file,
    parse_override_args,
    preset,
    resolve,
)
from ogmapping.config.fields import check
from ogmapping.optim.keyframes import FIXED_WINDOWS
from ogmapping.optim.refine import GROWTH

GOLDEN = Path(__file__).parent / "golden" / "presets.json"


def resolved_presets() -> str:
    """Every preset resolved with no overrides, as the golden file holds them."""
    return json.dumps({name: resolve(name).to_dict() for name in PRESETS}, indent=2, sort_keys=True) + "\n"


def test_presets_resolve_to_the_golden_file():
    """Each preset's every value, compared as text so that 1 and 1.0 differ; a change to a preset is
    deliberate: rewrite the file with ``python tests/test_config.py`` and say why in the commit."""
    assert resolved_presets() == GOLDEN.read_text()


def test_overrides_are_typed_and_checked():
    config = resolve("sparse", overrides=parse_override_args(["keyframes.iterations=7", "octree.voxel_size=0.2"]))
    assert config.keyframes.iterations == 7 and config.octree.voxel_size == 0.2
    with pytest.raises(ValueError, match="unknown config key"):
        resolve("sparse", overrides={"keyframes.nope": 1})
    with pytest.raises(ValueError, match="expects int"):
        resolve("sparse", overrides={"keyframes.iterations": "many"})
    with pytest.raises(ValueError, match="out of range"):
        resolve("sparse", overrides={"octree.voxel_size": "-1"})
    with pytest.raises(ValueError, match="unknown preset"):
        preset("fastest")


def test_a_stored_config_with_a_retired_key_loads_as_its_successor():
    stored = resolve("sparse").to_dict()
    del stored["poses"]["track_stride"]
    stored["poses"]["track_scale"] = 0.5  # stored before tracking sampled pixels by stride
    assert MapperConfig.from_dict(stored) == resolve("sparse")
    stored["poses"]["track_scale"] = 1.0
    assert MapperConfig.from_dict(stored).poses.track_stride == 1
    with pytest.raises(ValueError, match="unknown"):
        resolve("sparse", overrides={"poses.track_scale": "0.5"})  # not a key a client may set


def test_dict_round_trip_and_files(tmp_path):
    config = resolve("dense", overrides={"refine.interval": 5})
    assert MapperConfig.from_dict(config.to_dict()) == config
    path = tmp_path / "overrides.json"
    path.write_text(json.dumps({"loss": {"depth": 0.25}}))
    assert load_file(path) == {"loss.depth": 0.25}
    yaml_path = tmp_path / "overrides.yaml"
    yaml_path.write_text("keyframes:\n  local_count: 4\n")
    assert resolve("sparse", yaml_path).keyframes.local_count == 4
    both = resolve("sparse", yaml_path, {"keyframes.local_count": "6", "keyframes.iterations": "3"})
    assert (both.keyframes.local_count, both.keyframes.iterations) == (6, 3), "--set-style overrides win over the file"


def test_ablation_switches_default_to_the_paper_and_are_validated():
    config = preset("sparse")
    assert (config.octree.allocation, config.refine.growth, config.keyframes.window) == ("octree", "anchor", "dynamic")
    for key, value in (("octree.allocation", "unique"), ("octree.allocation", "projection"),
                       ("refine.growth", "error"), ("refine.growth", "none"),
                       ("keyframes.window", "random"), ("keyframes.window", "overlap"),
                       ("keyframes.window", "coverage")):
        resolve("sparse", overrides={key: value})
    for key, allowed in (("octree.allocation", "octree, unique, projection"),
                         ("refine.growth", "anchor, error, none"),
                         ("keyframes.window", "dynamic, random, overlap, coverage"),
                         ("model.encoding", "hash, anchor"),
                         ("model.anchor_colour_start", "zero, cell"),
                         ("backend", "auto, torch, cpu, gsplat")):
        with pytest.raises(ValueError, match=f"config {key} must be one of {allowed}, got 'bogus'"):
            resolve("sparse", overrides={key: "bogus"})


def test_the_dispatch_tables_cover_their_choices_exactly():
    assert tuple(GROWTH) == get_args(Growth)
    assert ("dynamic", *FIXED_WINDOWS) == get_args(Window)
    assert get_args(Backend) == ("auto", *BACKENDS)


def test_every_number_has_its_range_beside_it():
    def numbers(section: object, prefix: str = "") -> list[tuple[str, dataclasses.Field]]:
        found = []
        for item in dataclasses.fields(section):
            value = getattr(section, item.name)
            if dataclasses.is_dataclass(value):
                found += numbers(value, f"{prefix}{item.name}.")
            elif isinstance(value, int | float) and not isinstance(value, bool):
                found.append((f"{prefix}{item.name}", item))
        return found

    unbounded = [key for key, item in numbers(MapperConfig()) if "range" not in item.metadata]
    assert not unbounded


@pytest.mark.parametrize(("key", "value"), [
    ("octree.depth_min", "-1"),  # once reported as a depth_max error
    ("keyframes.first_iterations", "-5"),  # once accepted
    ("model.hidden_dim", "0"),
    ("model.hash_log2_size", "40"),
    ("octree.voxel_size", "inf"),
    ("octree.depth_max", "nan"),
    ("refine.grad_threshold", "-1"),
    ("refine.max_new_anchors", "-1"),
    ("loss.color", "nan"),
    ("optim.hash_lr", "-0.1"),
    ("optim.offsets_lr", "38695"),  # Gaussians thrown out of the map
    ("loss.depth", "1e300"),  # an infinite float32 loss
    ("seed", str(1 << 70)),  # beyond what torch's generator takes
    ("octree.allocation_stride", str(1 << 70)),  # once an INTERNAL error in torch's slicing (fuzzer)
    ("optim.average_decay", "1"),  # an average that never moves
    ("optim.average_decay", "-0.5"),
    ("optim.average_growth", "1.5"),  # a share of the map's steps
    ("optim.average_growth", "-0.1"),
    ("optim.second_moment_decay", "1"),  # Adam's running mean of squared gradients that never moves
    ("optim.second_moment_decay", "-0.1"),
    ("model.initial_visible", "1.5"),  # a share
    ("model.initial_visible", "nan"),
])
def test_every_range_check_names_its_own_key(key: str, value: str):
    with pytest.raises(ValueError, match=rf"^config {key} is out of range: must be "):
        resolve("sparse", overrides={key: value})


def test_server_bounds_refuse_costly_configs_and_can_be_tightened():
    bounds = ConfigBounds()
    for name in PRESETS:
        resolve(name, bounds=bounds)
    for key, value, named in (
        ("keyframes.first_iterations", "1000000", "config_bounds.max_iterations"),
        ("model.hash_log2_size", "24", "config_bounds.max_hash_table_mib"),  # 2 GiB of table
        ("octree.voxel_size", "0.001", "config_bounds.min_voxel_size"),
        ("keyframes.global_count", "100", "config_bounds.max_window_keyframes"),
    ):
        with pytest.raises(ValueError, match=rf"^config {key.split('.')[0]}.*{named}"):
            resolve("dense", overrides={key: value}, bounds=bounds)
        resolve("dense", overrides={key: value} if key != "model.hash_log2_size" else {})  # no bounds: accepted
    tightened = ConfigBounds(max_iterations=10)
    with pytest.raises(ValueError, match=r"keyframes.first_iterations = 60 is above this server's limit of 10"):
        resolve("dense", bounds=tightened)
    with pytest.raises(ValueError, match=r"^settings config_bounds.max_iterations is out of range: must be >= 1"):
        check(ConfigBounds(max_iterations=0), "settings", "config_bounds.")
    # The level a resolution rule may set on the first frame counts against the bound before any frame arrives
    # (tests/test_resolution_rules.py).

if __name__ == "__main__":
    GOLDEN.write_text(resolved_presets())
