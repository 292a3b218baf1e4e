"""The server's messages from typed results: the final stats an older server recorded are rebuilt exactly."""

from __future__ import annotations

import json
from pathlib import Path

from ogapi import recording
from ogserver.api import messages
from ogserver.sessions.counters import SessionCounters

from ogmapping.stats import MapStats

COMPAT = Path(__file__).resolve().parents[1] / "compat"


def test_stats_rebuild_the_message_recorded_before_the_typed_records() -> None:
    recorded = recording.load(COMPAT / "recording.mcap")
    old = recorded.stats
    fields = json.loads(old.engine_json)
    engine = MapStats(**{
        **fields,
        "anchors_per_level": tuple(fields["anchors_per_level"]),
        "octree_cells_per_level": tuple(fields["octree_cells_per_level"]),
    })
    counters = SessionCounters(
        received=old.frames_received, rejected=old.frames_rejected, mapped=old.frames, pending=old.queue_depth,
        skipped=old.frames_skipped,
        anchors=old.anchors, processing_fps=old.processing_fps, uptime_seconds=old.uptime_seconds,
    )
    rebuilt = messages.stats(recorded.config, engine, counters)
    assert rebuilt.engine_json == old.engine_json  # byte for byte: key order, lists, float repr
    assert rebuilt == old
