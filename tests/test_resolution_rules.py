"""The resolution rules as data (``ogmapping.config.resolution``): the step multiple, each kind of rule, the
presets' table resolved, refusals that name the rule, retired switches, bounds and ``ogmap config``."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from ogmapping.cli.commands import main
from ogmapping.config import ConfigBounds, MapperConfig, resolution, resolve
from ogmapping.config.resolution import follow, highest, step_multiple

COMPAT = Path(__file__).parent / "compat" / "presets_with_switches.json"


@pytest.mark.parametrize(("width", "height", "multiple"), [
    (160, 120, 1), (320, 240, 1), (600, 340, 1), (640, 480, 1),  # every size the presets were tuned at
    (1200, 680, 2), (1280, 720, 2), (1920, 1080, 3),
])
def test_the_multiple_follows_the_linear_size(width: int, height: int, multiple: int) -> None:
    assert step_multiple(204000, width, height) == multiple


def test_a_zero_reference_never_scales() -> None:
    assert step_multiple(0, 1920, 1080) == 1


def test_each_kind_of_rule() -> None:
    assert follow("none", 5, 3) == 5
    assert follow("linear", 5, 3) == 15 and follow("area", 5, 3) == 45
    assert follow("area", 5, 3, cap=32) == 32
    assert follow("inverse", 1.5e-4, 2) == 0.75e-4
    assert follow("0.8 from 2", 0.1, 1) == 0.1 and follow("0.8 from 2", 0.1, 2) == 0.8
    assert follow("true from 3", False, 2) is False and follow("true from 3", False, 3) is True


# What each preset resolves to at 1200x680 (a multiple of 2); every size up to about 900x510 keeps the preset.
AT_1200X680 = {
    "sparse": {"keyframes.step_multiple": 2, "model.n_offsets": 20, "octree.max_level": 2, "loss.ssim": 0.8,
               "refine.grad_threshold": 0.75e-4, "model.anchor_colour": True, "optim.average_decay": 0.85},
    "dense": {"keyframes.step_multiple": 4, "model.n_offsets": 10, "model.hash_max_resolution": 256.0,
              "octree.max_level": 2, "loss.ssim": 0.8, "refine.grad_threshold": 0.75e-4},
    "sparse-fast": {"keyframes.step_multiple": 2, "model.n_offsets": 10, "model.anchor_colour": True,
                    "loss.ssim": 0.4, "refine.grad_threshold": 1e-4, "optim.average_decay": 0.85},
}


@pytest.mark.parametrize("name", AT_1200X680)
def test_the_presets_table_resolves_purely_and_clears_every_rule(name: str) -> None:
    config = resolve(name)
    resolved = resolution.resolve(config, step_multiple(config.resolution.reference_pixels, 1200, 680))
    assert config == resolve(name), "the caller's config is left as it was"
    for key, value in AT_1200X680[name].items():
        section, field = key.split(".")
        assert getattr(getattr(resolved.config, section), field) == value, key
    assert not resolution.pending(resolved.config)
    assert resolved.reshaped
    assert resolution.resolve(config, 1).config.to_dict() == {
        **config.to_dict(), "resolution": resolved.config.to_dict()["resolution"]}


@pytest.mark.parametrize(("key", "value", "message"), [
    ("resolution.steps", "inverse", r"resolution.steps must be 'none' or 'linear' or 'area' or 'VALUE from M'"),
    ("resolution.anchor_colour", "linear", r"resolution.anchor_colour must be 'none' or 'VALUE from M'"),
    ("resolution.max_level", "9 from 2", r"resolution.max_level = '9 from 2': config octree.max_level is out of "
                                         r"range"),
    ("resolution.anchor_colour", "2 from 2", r"resolution.anchor_colour = '2 from 2': expects true or false"),
    ("resolution.n_offsets", "2.5 from 2", r"resolution.n_offsets = '2.5 from 2': expects int"),
    ("resolution.ssim", "0.8 from 0", r"resolution.ssim must be"),
])
def test_a_rule_a_setting_cannot_take_is_refused_by_name(key: str, value: str, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        resolve("sparse", overrides={key: value})


def test_configs_stored_with_the_switches_load_as_the_rules_they_stood_for() -> None:
    # Stored before `keyframes.global_draw`, `sparse`'s fourth global keyframe, its keyframe poses refined in
    # the window and its Adam's shorter memory, they load with the uniform draw, the window, the poses and the
    # Adam their maps were made with.
    window_then = {"sparse": {"keyframes.global_count": 3, "poses.refine": False, "poses.track_iterations": 2,
                              "poses.track_newton_iterations": 4, "poses.view_steps": True,
                              "poses.mapping_rate": 1.0, "poses.review": False,
                              "optim.second_moment_decay": 0.999}}
    for name, stored in json.loads(COMPAT.read_text()).items():
        overrides = {"keyframes.global_draw": "random", **window_then.get(name, {})}
        assert MapperConfig.from_dict(stored) == resolve(name, overrides=overrides), name
    cleared = resolve("sparse").to_dict()  # what a snapshot stored once its first frame resolved the switches
    del cleared["resolution"]
    cleared["keyframes"].update(steps_reference_pixels=204000, steps_growth="area")
    cleared["model"].update(offsets_by_resolution=False, offsets_growth="area")
    loaded = MapperConfig.from_dict(cleared)
    assert loaded.resolution.steps == "area" and loaded.resolution.n_offsets == "none"
    assert not resolution.reshape_pending(loaded)


def test_bounds_count_what_the_rules_may_make() -> None:
    config = resolve("sparse")
    assert highest(config, "max_level") == 2 and highest(config, "n_offsets") == 32
    levels = ConfigBounds(max_octree_level=1)
    resolve("sparse", overrides={"resolution.max_level": "none"}, bounds=levels)
    with pytest.raises(ValueError, match=r"octree.max_level \(at most, by resolution.max_level\) = 2 is above this "
                                         r"server's limit of 1"):
        resolve("sparse", bounds=levels)
    with pytest.raises(ValueError, match=r"model.n_offsets \(at most, by resolution.n_offsets\) = 32 is above"):
        resolve("sparse", bounds=ConfigBounds(max_n_offsets=8))
    resolve("sparse", overrides={"resolution.n_offsets": "none"}, bounds=ConfigBounds(max_n_offsets=8))


def test_ogmap_config_prints_each_rule_and_its_value(capsys) -> None:
    assert main(["config", "--preset", "sparse", "--resolution", "1200x680"]) == 0
    out = capsys.readouterr().out
    assert "sparse at 1200x680: step multiple 2" in out
    assert "model.n_offsets            area        5 -> 20" in out
    assert main(["config", "--preset", "dense", "--resolution", "1200x680", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["keyframes"]["step_multiple"] == 4
    assert main(["config", "--preset", "dense", "--resolution", "big"]) == 2
    assert "--resolution must be WIDTHxHEIGHT" in capsys.readouterr().err
