"""A user's session through the CLI: real frames in, renders, a snapshot, a restore, the recording back.

The frames are 7-Scenes from ../shared (the synthetic room where ../shared is absent). The container
test (docker/container-test.sh) runs this module in a test container against the server container,
with ../shared mounted beside the tests and one recordings volume at the same path in both; here it
runs against a subprocess server like every other module. Unlike test_integration, which skips its
recording checks when the server's files are out of sight, this module needs them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from ogapi import recording
from ogapi.images import decode_color
from ogapi.v1 import mapping_pb2 as pb
from ogclient.__main__ import main as ogclient_main
from ogclient.connection import SessionRef
from ogclient.evaluation import evaluate, render

from ogmapping.quality.evaluation import FrameSet, open_frames

from .conftest import ServerHandle
from .scene import TINY

FRAMES = "0:12"  # 11 streamed positions, position 5 held out
SCALE = 0.25  # 7-Scenes' 640x480 -> 160x120, inside docker/test-server.yaml's max_image_pixels


@dataclass
class Dataset:
    flags: list[str]  # the CLI's dataset flags
    frames: FrameSet


@dataclass
class Streamed:
    session: SessionRef
    folder: Path


def cli(server: ServerHandle, *args: str | Path) -> int:
    return ogclient_main(["--server", server.address, *map(str, args)])


@pytest.fixture(scope="module")
def dataset(seven_scenes_if_present: Path | None) -> Dataset:
    data, format = (str(seven_scenes_if_present), "7scenes") if seven_scenes_if_present else ("synthetic", "synthetic")
    flags = ["--data", data, "--format", format, "--frames", FRAMES, "--scale", str(SCALE)]
    return Dataset(flags, open_frames(data, format, FRAMES, 1, SCALE))


@pytest.fixture(scope="module")
def streamed(server: ServerHandle, dataset: Dataset, tmp_path_factory: pytest.TempPathFactory) -> Streamed:
    folder = tmp_path_factory.mktemp("real")
    overrides = [flag for key, value in TINY.items() for flag in ("--set", f"{key}={value}")]
    assert cli(server, "stream", *dataset.flags, "--preset", "sparse-fast", *overrides, "--label", "real",
               "--session-out", folder / "session.json", "--quiet") == 0
    return Streamed(SessionRef.load(folder / "session.json"), folder)


def stats(server: ServerHandle, session: SessionRef) -> pb.Stats:
    return server.stub.GetStats(pb.GetStatsRequest(session_id=session.session_id), metadata=session.metadata())


def test_every_frame_is_mapped(server: ServerHandle, dataset: Dataset, streamed: Streamed) -> None:
    current = stats(server, streamed.session)
    assert current.frames == len(dataset.frames.selection.streamed) and current.frames_rejected == 0
    assert current.anchors > 0 and current.keyframes > 0


def test_renders_resemble_the_frames(server: ServerHandle, dataset: Dataset, streamed: Streamed) -> None:
    results = evaluate(server.stub, streamed.session, dataset.frames, out=streamed.folder / "eval", progress=False)
    camera = dataset.frames.load(0).color_intrinsics
    assert results["resolution"] == [camera.width, camera.height]
    for split in ("streamed", "heldout"):
        assert results[split]["psnr"] > 12.0 and np.isfinite(results[split]["depth_l1_cm"]), (split, results[split])


def test_a_restored_snapshot_renders_like_the_original(server: ServerHandle, dataset: Dataset,
                                                       streamed: Streamed) -> None:
    snapshot, restored_file = streamed.folder / "map.safetensors", streamed.folder / "restored.json"
    assert cli(server, "snapshot", "--session", streamed.folder / "session.json", "--out", snapshot) == 0
    assert cli(server, "restore", snapshot, "--session-out", restored_file, "--label", "restored") == 0
    restored = SessionRef.load(restored_file)
    try:
        assert stats(server, restored).anchors == stats(server, streamed.session).anchors
        for position in (dataset.frames.selection.streamed[-1], dataset.frames.selection.heldout[0]):
            frame = dataset.frames.load(position)
            original = render(server.stub, streamed.session, frame.c2w, frame.color_intrinsics)
            again = render(server.stub, restored, frame.c2w, frame.color_intrinsics)
            # Snapshots keep the hash table in float16 (tests/test_snapshot.py): close, not equal.
            assert np.abs(again.color - original.color).mean() < 2e-3
            assert np.abs(again.depth - original.depth).mean() < 2e-3
    finally:
        assert cli(server, "close", "--session", restored_file) == 0


def test_the_recording_holds_every_frame(server: ServerHandle, dataset: Dataset, streamed: Streamed) -> None:
    closed = server.stub.CloseSession(pb.CloseSessionRequest(session_id=streamed.session.session_id),
                                      metadata=streamed.session.metadata())
    path = server.recorded(closed.recording)
    assert path is not None, f"{closed.recording}: the server's record dir must be visible here ($OGMAP_RECORD_DIR)"
    recorded = recording.load(path)
    assert [frame.index for _, frame in recorded.frames] == dataset.frames.selection.streamed
    assert recorded.stats is not None and recorded.stats.anchors == closed.stats.anchors
    first = recorded.frames[0][1]
    sent = dataset.frames.load(first.index)
    height, width = sent.rgb.shape[:2]
    decoded = decode_color(first.color.data, first.color.encoding, width, height)
    assert np.abs(decoded - sent.rgb).max() <= 0.5 / 255 + 1e-6
