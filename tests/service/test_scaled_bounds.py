"""What the resolution rules make of a session's config stays within the operator's bounds, the image size
they count from is the operator's, and the stats say what the map really uses."""

from __future__ import annotations

import json

import grpc
import pytest
from ogapi.v1 import mapping_pb2 as pb
from ogserver.api import messages
from ogserver.errors import ServiceError
from ogserver.sessions.counters import SessionCounters
from ogserver.sessions.registry import requested_config
from ogserver.settings import Settings

from ogmapping.config import ConfigBounds
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.mapper import Mapper

COUNTERS = SessionCounters(received=1, rejected=0, mapped=1, pending=0, skipped=0, anchors=0, processing_fps=0.0,
                           uptime_seconds=0.0)


def test_a_client_may_not_set_the_image_size_the_step_multiple_counts_from() -> None:
    """4800 pixels made a 160x120 frame count as a multiple of 2: four times the Gaussians an anchor."""
    request = pb.CreateSessionRequest(preset="sparse", overrides={"resolution.reference_pixels": "4800"})
    with pytest.raises(ServiceError) as refusal:
        requested_config(request, Settings())
    assert refusal.value.code == grpc.StatusCode.INVALID_ARGUMENT
    assert "resolution_reference_pixels" in refusal.value.message
    pinned = pb.CreateSessionRequest(preset="sparse", overrides={"resolution.reference_pixels": "204000"})
    assert requested_config(pinned, Settings())[2].resolution.reference_pixels == 204000  # a replay pins it


def test_scaled_steps_stay_within_the_bounds_and_the_stats_say_what_the_map_uses() -> None:
    settings = Settings(config_bounds=ConfigBounds(max_iterations=100), resolution_reference_pixels=4800)
    _, overrides, config = requested_config(pb.CreateSessionRequest(preset="sparse"), settings)
    assert overrides["resolution.reference_pixels"] == "4800"  # the recording replays with the server's value
    mapper = Mapper(config, "cpu", bounds=settings.config_bounds)
    mapper.process(SyntheticSource(n_frames=1, width=160, height=120)[0])  # a step multiple of 2 here
    used = mapper.config
    assert used.model.n_offsets == 20, "Gaussians an anchor follow the multiple (area): 5 x 2^2"
    steps = (used.keyframes.first_iterations, used.keyframes.iterations, used.keyframes.frame_iterations)
    assert all(count * used.keyframes.step_multiple <= 100 for count in steps), (steps, used.keyframes.step_multiple)
    assert mapper.stats().iterations <= 100
    created = pb.SessionConfig(config_json=json.dumps(config.to_dict()))
    reported = json.loads(messages.stats(created, mapper.stats(), COUNTERS).config_json)
    assert reported["model"]["n_offsets"] == 20
    assert reported["keyframes"]["step_multiple"] == used.keyframes.step_multiple
