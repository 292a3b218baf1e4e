"""Stream a session recording into a new session, as fast as possible or at the recorded rate."""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterator

from ogapi.recording import Recording
from ogapi.v1 import mapping_pb2 as pb

from ogmapping.config import pinned


def session_request(config: pb.SessionConfig | None, label: str = "") -> pb.CreateSessionRequest:
    """The recorded session's whole resolved config, on top of its preset: a replay rebuilds the
    recorded map even after a later version changed the preset's defaults. A recording without
    the resolved config (none, or an empty one) falls back to its preset and overrides."""
    if config is None:
        return pb.CreateSessionRequest(label=label)
    preset, overrides = pinned(config.preset, config.overrides, config.config_json)
    return pb.CreateSessionRequest(preset=preset, overrides=overrides, label=label)


def recorded_times(recording: Recording) -> list[float]:
    """Seconds from the first frame: sensor timestamps when every frame has one and they
    increase, else arrival times."""
    frames = [frame for _, frame in recording.frames]
    stamps = [frame.timestamp for frame in frames]
    if all(frame.HasField("timestamp") for frame in frames) and all(b > a for a, b in itertools.pairwise(stamps)):
        return [s - stamps[0] for s in stamps]
    arrivals = [log_ns for log_ns, _ in recording.frames]
    return [(t - arrivals[0]) / 1e9 for t in arrivals]


def frames(recording: Recording, realtime: bool = False, first: int = 0,
           end: int | None = None) -> Iterator[pb.Frame]:
    """The recorded Frame messages ``first`` to ``end`` (list positions), unchanged, optionally paced like the
    original stream (from the first of them)."""
    offsets = recorded_times(recording) if realtime else [0.0] * len(recording.frames)
    chosen = slice(first, end)
    start = time.monotonic()
    for offset, (_, frame) in zip(offsets[chosen], recording.frames[chosen], strict=True):
        delay = offset - offsets[first] - (time.monotonic() - start)
        if delay > 0:
            time.sleep(delay)
        yield frame
