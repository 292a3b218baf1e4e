"""What older code wrote still loads and replays the same (tests/compat/, made at commit 03e848c)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from ogapi import recording
from ogclient.__main__ import main as ogclient_main
from ogclient.connection import SessionRef
from ogclient.evaluation import render
from safetensors.numpy import load_file

from ogmapping.frames.camera import Intrinsics
from ogmapping.mapper import Mapper
from ogmapping.quality.metrics import psnr

COMPAT = Path(__file__).resolve().parents[1] / "compat"


def expected() -> tuple[np.ndarray, Intrinsics, dict[str, np.ndarray]]:
    stored = load_file(COMPAT / "render.safetensors")
    fx, fy, cx, cy, width, height = stored["intrinsics"].tolist()
    return stored["c2w"], Intrinsics(fx, fy, cx, cy, int(width), int(height)), stored


def test_an_old_snapshot_renders_as_it_did() -> None:
    c2w, camera, stored = expected()
    mapper = Mapper.restore((COMPAT / "snapshot.safetensors").read_bytes())
    rendered = mapper.render(c2w, camera)
    # The live map rendered these images; its snapshot keeps the learnable tensors in float16
    # (80 dB when the fixture was made).
    assert psnr(rendered.color, stored["color"]) > 60.0
    assert np.abs(rendered.depth - stored["depth"]).max() < 0.02


def test_an_old_recording_replays_to_the_same_map(server, tmp_path) -> None:
    c2w, camera, stored = expected()
    recorded = recording.load(COMPAT / "recording.mcap")
    assert len(recorded.frames) == 9 and recorded.config.preset == "sparse-fast"
    session_file = tmp_path / "session.json"
    code = ogclient_main(["--server", server.address, "replay", str(COMPAT / "recording.mcap"),
                          "--session-out", str(session_file), "--quiet"])
    assert code == 0
    session = SessionRef.load(session_file)
    rendered = render(server.stub, session, c2w, camera)
    # Identical on the machine that made the fixture; other CPUs round differently.
    assert psnr(rendered.color, stored["color"]) > 40.0, "the replayed map differs from the recorded one"
    assert np.abs(rendered.depth - stored["depth"]).mean() < 0.01
