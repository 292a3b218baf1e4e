"""One count of a map's Gaussians wherever the whole map is meant: ``ogmap export``, the web view's panel
(labelled "gaussians in map") and the demo's summary."""

from __future__ import annotations

import re

from ogclient import demo
from ogserver.web.maps import MapView
from ogserver.web.still import open_map

from ogmapping.cli.commands import main as ogmap


def test_export_web_panel_and_demo_count_the_same_gaussians(tmp_path, tiny_snapshot, capsys) -> None:
    snapshot = tiny_snapshot
    assert ogmap(["export", "--snapshot", str(snapshot), "--out", str(tmp_path / "map.ply")]) == 0
    exported = int(re.match(r"wrote (\d+) Gaussians", capsys.readouterr().out).group(1))

    view = MapView(open_map(snapshot, "cpu", print), 0.0)
    assert view.splats(None).count == exported
    stats = view.state()["stats"]
    assert stats["gaussians_in_map"] == exported and "gaussians_drawn" not in stats

    assert demo.map_gaussians(snapshot.read_bytes()) == exported
