"""Replay pacing, the session a replay asks for, and where it applies recorded pose corrections."""

from __future__ import annotations

import json
from pathlib import Path

from ogapi.recording import Recording, load
from ogapi.v1 import mapping_pb2 as pb
from ogclient.corrections import segments
from ogclient.replay import recorded_times, session_request


def recording(stamps: list[float], arrivals_ns: list[int]) -> Recording:
    frames = [(arrival, pb.Frame(index=i, timestamp=stamp)) for i, (stamp, arrival) in
              enumerate(zip(stamps, arrivals_ns, strict=True))]
    return Recording(config=None, frames=frames, acks=[], stats=None)


def test_sensor_timestamps_set_the_pace_when_they_increase() -> None:
    assert recorded_times(recording([10.0, 10.5, 11.0], [0, 5, 9])) == [0.0, 0.5, 1.0]


def test_arrival_times_set_the_pace_otherwise() -> None:
    assert recorded_times(recording([0.0, 0.0, 0.0], [1_000_000_000, 1_500_000_000, 3_000_000_000])) == \
        [0.0, 0.5, 2.0]


def test_session_request_repeats_the_recorded_config() -> None:
    recorded = {"keyframes": {"iterations": 3, "window_scale": 0.5}, "seed": 0}
    fresh = pb.SessionConfig(preset="sparse-fast", overrides={"keyframes.iterations": "3"},
                             config_json=json.dumps(recorded))
    request = session_request(fresh, "again")
    assert (request.preset, request.label) == ("sparse-fast", "again")
    # Every resolved value is pinned, so later changes to the preset's defaults do not change a replay.
    assert dict(request.overrides) == {"keyframes.iterations": "3", "keyframes.window_scale": "0.5", "seed": "0"}
    restored = pb.SessionConfig(config_json=json.dumps({"keyframes": {"iterations": 7}, "seed": 0}))
    request = session_request(restored)
    assert request.preset == "dense" and dict(request.overrides) == {"keyframes.iterations": "7", "seed": "0"}
    legacy = pb.SessionConfig(preset="sparse", overrides={"seed": "2"})
    assert dict(session_request(legacy).overrides) == {"seed": "2"}


def test_replay_segments_cut_where_corrections_were_applied() -> None:
    frames = [(i, pb.Frame(index=i)) for i in range(5)]
    batches = [pb.PoseCorrections(after_sequence=2), pb.PoseCorrections(after_sequence=5)]
    cut = list(segments(Recording(config=None, frames=frames, acks=[], stats=None, corrections=batches)))
    assert [(segment.start, segment.end, segment.corrections) for segment in cut] == \
        [(0, 2, batches[0]), (2, 5, batches[1])]
    plain = list(segments(Recording(config=None, frames=frames, acks=[], stats=None)))
    assert [(segment.start, segment.end, segment.corrections) for segment in plain] == [(0, 5, None)]


def test_recordings_from_before_corrections_hold_none() -> None:
    old = load(Path(__file__).resolve().parents[1] / "compat" / "recording.mcap")
    assert old.frames and old.corrections == []
