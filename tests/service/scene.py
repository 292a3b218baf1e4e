"""The tiny synthetic scene and session configurations every service test shares."""

from __future__ import annotations

from pathlib import Path

import yaml
from ogapi.convert import FrameEncoding
from ogapi.v1 import mapping_pb2 as pb
from ogclient.messages import frame_to_proto

from ogmapping.quality.evaluation import FrameSet, open_frames

REPO = Path(__file__).resolve().parents[2]
TEST_SERVER_CONFIG = REPO / "docker" / "test-server.yaml"
LIMITS = yaml.safe_load(TEST_SERVER_CONFIG.read_text())["limits"]

PRESET = "sparse-fast"
# A few optimisation steps: the map learns something, a session maps in seconds on a CPU.
TINY = {"keyframes.first_iterations": "6", "keyframes.iterations": "2"}
# No optimisation at all: anchors are allocated but nothing is trained; for tests of plumbing.
FROZEN = {"keyframes.first_iterations": "0", "keyframes.iterations": "0"}
FRAMES = "0:10"  # 9 streamed positions, position 5 held out
SCALE = 0.25  # 320x240 -> 80x60


def scene(frames: str = FRAMES) -> FrameSet:
    return open_frames("synthetic", "synthetic", frames, 1, SCALE, n_frames=40)


def messages(frame_set: FrameSet, encoding: FrameEncoding | None = None) -> list[pb.Frame]:
    encoding = encoding or FrameEncoding()
    return [frame_to_proto(frame_set.load(p), encoding) for p in frame_set.selection.streamed]


def create_request(overrides: dict[str, str], label: str = "test") -> pb.CreateSessionRequest:
    return pb.CreateSessionRequest(preset=PRESET, overrides=overrides, label=label)
