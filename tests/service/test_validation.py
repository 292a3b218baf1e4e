"""Server-side validation without a server: each bad field gets its status code and its name."""

from __future__ import annotations

import numpy as np
import pytest
from ogapi.images import encode_color, encode_depth
from ogapi.v1 import mapping_pb2 as pb
from ogclient.messages import frame_to_proto
from ogserver.api import validation
from ogserver.errors import ServiceError

from ogmapping.config import OctreeConfig

from .bad_frames import CASES, INVALID, broken
from .proto_names import assert_spelled_as_the_proto
from .scene import scene

MAX_PIXELS = 65536
OCTREE = OctreeConfig()
GOOD = frame_to_proto(scene("0:1").load(0))


@pytest.mark.parametrize("case", list(CASES))
def test_bad_frame_is_refused(case: str) -> None:
    change, code, field = CASES[case]
    with pytest.raises(ServiceError) as refusal:
        validation.frame(broken(GOOD, change), MAX_PIXELS, OCTREE)
    assert refusal.value.code == code and field in refusal.value.message
    assert_spelled_as_the_proto(refusal.value.message, pb.Frame.DESCRIPTOR)


@pytest.mark.parametrize(("encoding", "named"), [("color", "COLOR_JPEG, COLOR_PNG"), ("depth", "DEPTH_PNG16")])
def test_unknown_encodings_are_named_as_in_the_proto(encoding: str, named: str) -> None:
    message = broken(GOOD, lambda m: setattr(getattr(m, encoding), "encoding", 17))
    with pytest.raises(ServiceError) as refusal:
        validation.frame(message, MAX_PIXELS, OCTREE)
    assert named in refusal.value.message and "(got 17)" in refusal.value.message


def test_good_frame_decodes() -> None:
    frame = validation.frame(GOOD, MAX_PIXELS, OCTREE)
    assert frame.rgb.shape == (60, 80, 3) and frame.depth.shape == (60, 80)
    assert frame.registered and frame.c2w.shape == (4, 4)


def test_separate_depth_camera_is_kept() -> None:
    message = broken(GOOD, lambda m: m.depth_to_color.extend(np.eye(4).reshape(-1).tolist()))
    frame = validation.frame(message, MAX_PIXELS, OCTREE)
    assert frame.depth_to_color is not None and not frame.registered


@pytest.mark.parametrize(
    ("value", "code"),
    [("", INVALID), ("abc", INVALID), ("G" * 32, INVALID), ("0" * 32, None)],
)
def test_session_id_format(value: str, code) -> None:
    if code is None:
        assert validation.session_id(value) == value
    else:
        with pytest.raises(ServiceError) as refusal:
            validation.session_id(value)
        assert refusal.value.code == code and "session_id" in refusal.value.message


def render_request(**changes) -> pb.RenderRequest:
    request = pb.RenderRequest(c2w=np.eye(4).reshape(-1).tolist(), intrinsics=GOOD.color_intrinsics)
    for key, value in changes.items():
        if isinstance(value, list):
            getattr(request, key).extend(value)
        else:
            setattr(request, key, value)
    return request


def test_render_request_defaults_to_png_colour_and_depth() -> None:
    spec = validation.render_request(render_request(), MAX_PIXELS)
    assert spec.color and spec.depth
    assert (spec.color_encoding, spec.depth_encoding, spec.jpeg_quality) == (pb.COLOR_PNG, pb.DEPTH_PNG16, 90)
    assert spec.sequence is None and spec.timestamp is None  # the pose is in the map's frame


def test_a_render_request_names_the_frame_its_pose_is_from() -> None:
    assert validation.render_request(render_request(sequence=7), MAX_PIXELS).sequence == 7
    spec = validation.render_request(render_request(timestamp=12.5), MAX_PIXELS)
    assert (spec.sequence, spec.timestamp) == (None, 12.5)


@pytest.mark.parametrize(
    ("changes", "code", "field"),
    [
        ({"color_encoding": 9}, INVALID, "color_encoding"),
        ({"depth_encoding": 9}, INVALID, "depth_encoding"),
        ({"jpeg_quality": 101}, INVALID, "jpeg_quality"),
        ({"outputs": [7]}, INVALID, "outputs"),
        ({"sequence": 0}, INVALID, "sequence"),
        ({"timestamp": float("nan")}, INVALID, "timestamp"),
        ({"timestamp": float("inf")}, INVALID, "timestamp"),
    ],
)
def test_bad_render_request(changes: dict, code, field: str) -> None:
    with pytest.raises(ServiceError) as refusal:
        validation.render_request(render_request(**changes), MAX_PIXELS)
    assert refusal.value.code == code and refusal.value.message.startswith(field)
    assert_spelled_as_the_proto(refusal.value.message, pb.RenderRequest.DESCRIPTOR)


@pytest.mark.parametrize(("width", "height", "changes", "field"), [
    (70000, 1, {"color_encoding": pb.COLOR_JPEG, "outputs": [pb.RENDER_OUTPUT_COLOR]}, "JPEG images are at most"),
    (1, 12582912, {"outputs": [pb.RENDER_OUTPUT_COLOR]}, "PNG images are at most"),
    (1, 12582912, {"outputs": [pb.RENDER_OUTPUT_DEPTH]}, "PNG images are at most"),
])
def test_renders_no_encoding_can_hold_are_refused_before_rendering(width, height, changes, field) -> None:
    """70000x1 JPEG and 1x12582912 PNG renders were rendered, then failed to encode with INTERNAL."""
    side = max(width, height)
    camera = pb.CameraIntrinsics(fx=side, fy=side, cx=width / 2, cy=height / 2, width=width, height=height)
    request = render_request(**changes)
    request.intrinsics.CopyFrom(camera)
    with pytest.raises(ServiceError) as refusal:
        validation.render_request(request, 1 << 24)
    assert refusal.value.code == INVALID and refusal.value.message.startswith("intrinsics: ")
    assert field in refusal.value.message
    assert_spelled_as_the_proto(refusal.value.message, pb.RenderRequest.DESCRIPTOR)
    raw = render_request(color_encoding=pb.COLOR_RAW_RGB8, depth_encoding=pb.DEPTH_RAW_F32)
    raw.intrinsics.CopyFrom(camera)
    assert validation.render_request(raw, 1 << 24).intrinsics.width == width


def test_encoders_refuse_sizes_their_format_cannot_hold() -> None:
    with pytest.raises(ValueError, match="JPEG images are at most 65500 pixels a side"):
        encode_color(np.zeros((1, 70000, 3), np.uint8), pb.COLOR_JPEG)
    with pytest.raises(ValueError, match="PNG images are at most 1000000 pixels a side"):
        encode_depth(np.zeros((1_000_001, 1), np.float32), pb.DEPTH_PNG16)
