"""Presets and overrides."""

import json

import pytest

from ogmapping.config import MapperConfig, load_file, parse_override_args, preset, resolve


def test_presets_differ_as_the_paper_says():
    dense, sparse, fast = preset("dense"), preset("sparse"), preset("sparse-fast")
    assert dense.model.encoding == "hash" and sparse.model.encoding == "anchor"
    assert sparse.refine.prune_opacity > dense.refine.prune_opacity
    assert fast.keyframes.iterations < sparse.keyframes.iterations < dense.keyframes.iterations
    assert fast.keyframes.window_scale == sparse.keyframes.window_scale < dense.keyframes.window_scale == 1.0


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
                         ("keyframes.window", "dynamic, random, overlap, coverage")):
        with pytest.raises(ValueError, match=f"config {key} must be one of {allowed}, got 'bogus'"):
            resolve("sparse", overrides={key: "bogus"})
