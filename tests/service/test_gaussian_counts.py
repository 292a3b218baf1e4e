"""One count of a map's Gaussians wherever the whole map is meant (``ogmap export``, the web view's panel, the
demo's summary), and the engine's per-view count labelled as such."""

from __future__ import annotations

import re

from ogclient import demo
from ogserver.web.maps import MapView
from ogserver.web.still import StillMap

from ogmapping.cli.commands import main as ogmap
from ogmapping.config import resolve
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.mapper import Mapper


def test_export_web_panel_and_demo_count_the_same_gaussians(tmp_path, capsys) -> None:
    source = SyntheticSource(n_frames=3, width=64, height=48)
    mapper = Mapper(resolve("sparse", overrides={"keyframes.first_iterations": 2, "keyframes.iterations": 1}), "cpu")
    for position in range(len(source)):
        mapper.process(source[position])
    snapshot = tmp_path / "map.safetensors"
    snapshot.write_bytes(mapper.snapshot())

    assert ogmap(["export", "--snapshot", str(snapshot), "--out", str(tmp_path / "map.ply")]) == 0
    exported = int(re.match(r"wrote (\d+) Gaussians", capsys.readouterr().out).group(1))

    view = MapView(StillMap("map", "map.safetensors", Mapper.restore(snapshot.read_bytes(), "cpu")), 0.0)
    assert view.splats(None).count == exported
    stats = view.state()["stats"]
    assert stats["gaussians_in_map"] == exported and "gaussians_drawn" not in stats

    assert demo.map_gaussians(snapshot.read_bytes()) == exported
    assert 0 < mapper.stats().gaussians <= exported  # the last keyframe's view draws part of the map
