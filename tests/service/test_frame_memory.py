"""What a frame may cost a session is bounded by its pixels: a colour or depth image larger than
``limits.max_image_pixels`` (4096x3072 by default) is refused before it is decoded, naming the setting,
and the session maps the next frame as before."""

from __future__ import annotations

import grpc
from ogapi.v1 import mapping_pb2 as pb
from ogclient.connection import SessionRef
from ogserver.settings import Settings

from .inprocess import serving, settings
from .scene import FROZEN, create_request, messages, scene


def test_the_default_bound_is_a_4096_by_3072_frame() -> None:
    assert Settings().limits.max_image_pixels == 4096 * 3072


def test_a_frame_larger_than_the_bound_is_refused_naming_it_and_the_next_is_mapped(tmp_path) -> None:
    frames = messages(scene("0:2"))
    small, large = frames[0], pb.Frame()
    large.CopyFrom(frames[1])
    camera = small.color_intrinsics
    configured = settings(tmp_path)
    configured.limits.max_image_pixels = camera.width * camera.height
    for intrinsics in (large.color_intrinsics, large.depth_intrinsics):
        intrinsics.width, intrinsics.height = camera.width + 1, camera.height  # a column over the bound
    with serving(configured) as running:
        session = SessionRef.from_credentials(running.stub.CreateSession(create_request(FROZEN)))
        acks = list(running.stub.StreamFrames(iter([large, small]), metadata=session.stream_metadata(), timeout=60))
        refused, mapped = acks
        assert not refused.accepted
        assert refused.error.code_name == grpc.StatusCode.RESOURCE_EXHAUSTED.name
        assert "limits.max_image_pixels" in refused.error.message
        assert f"{camera.width * camera.height} pixels" in refused.error.message
        assert mapped.accepted
