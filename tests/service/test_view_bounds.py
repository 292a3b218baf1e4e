"""A shared snapshot opened in the web view (``ogserver view``, ``ogclient view``) is held to the server's
config bounds before anything is built for it: a small file naming a huge model is one line and exit 2."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from ogserver import view
from ogserver.web import still
from safetensors.torch import save as save_tensors

from ogmapping.config import resolve
from ogmapping.mapper import Mapper
from ogmapping.persist import snapshot


def crafted(tmp_path: Path) -> Path:
    """A snapshot of a few anchors whose config asks for a 512 MiB hash table (the bound is 256 MiB)."""
    mapper = Mapper(resolve("dense", overrides={"keyframes.first_iterations": 1}))
    config = mapper.state().config.to_dict()
    config["model"]["hash_log2_size"] = 22
    metadata = snapshot.read_metadata(mapper.snapshot())
    path = tmp_path / "shared.safetensors"
    path.write_bytes(save_tensors({"anchors.codes": mapper.state().tensors["anchors.codes"]},
                                  metadata={**metadata, "config": json.dumps(config)}))
    return path


def test_a_snapshot_beyond_the_config_bounds_is_refused_before_it_is_built(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match=r"config_bounds\.max_hash_table_mib"):
        still.open_map(crafted(tmp_path), "cpu", print)


def test_ogserver_view_says_so_in_one_line_and_exits_2(tmp_path: Path, capsys) -> None:
    assert view.main([str(crafted(tmp_path)), "--device", "cpu"]) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and error[0].startswith(view.ERROR_PREFIX) and "max_hash_table_mib" in error[0]
