"""What a client can send, against a real server: configs beyond the server's bounds, and hypothesis
throwing random and mutated Frame, RenderRequest and CreateSessionRequest messages. No call ends in
INTERNAL, none hangs (every call has a timeout), and the session still maps and renders afterwards.
Each fuzz test is bounded by its example count and the calls' timeouts."""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Callable, Iterator

import grpc
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from ogapi.v1 import mapping_pb2 as pb
from ogclient.connection import SessionRef, connect
from ogclient.messages import frame_to_proto
from ogserver.api.validation import MAX_TIMESTAMP_SECONDS
from safetensors.torch import load as load_tensors
from safetensors.torch import save as save_tensors

from ogmapping.config import MapperConfig, flatten, resolve
from ogmapping.mapper import Mapper
from ogmapping.persist.snapshot import read_metadata

from .conftest import ServerHandle, start_local
from .scene import PRESET, TINY, create_request, scene

CALL_SECONDS = 30.0  # any call still running then counts as hung


def fuzz(examples: int) -> settings:
    """A few seconds each on a CPU; no example database (a failure prints the blob that reproduces it)."""
    return settings(max_examples=examples, deadline=None, database=None, print_blob=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


GOOD = frame_to_proto(scene("0:2").load(0))
NEXT = frame_to_proto(scene("0:2").load(1))
Mutation = Callable[[pb.Frame], None]

# Numbers that sit on the edges of what fields, the engine and the codecs take.
EDGE_FLOATS = st.sampled_from([0.0, -0.0, 1e-300, -1.0, 1e300, math.inf, -math.inf, math.nan, 7000.0, 0.5, 1e6])
FLOATS = EDGE_FLOATS | st.floats(allow_nan=True, allow_infinity=True) | st.floats(-500, 500)
TIMESTAMP_EDGES = st.sampled_from([
    MAX_TIMESTAMP_SECONDS, math.nextafter(MAX_TIMESTAMP_SECONDS, 0.0), math.nextafter(MAX_TIMESTAMP_SECONDS, math.inf),
    -5e-324, 5e-324, -1e-9, 1.8e308, -1.8e308, 2.0**63 / 1e9,
]) | st.floats(-2 * MAX_TIMESTAMP_SECONDS, 2 * MAX_TIMESTAMP_SECONDS)
SIZES = st.sampled_from([0, 1, 59, 60, 61, 80, 65500, 70000, 100000, 2**32 - 1]) | st.integers(0, 300)
BYTES = st.binary(max_size=512) | st.sampled_from([b"\x89PNG\r\n\x1a\n", b"\xff\xd8", GOOD.color.data[:40]])


def set_value(path: str, value: object) -> Mutation:
    def change(message: pb.Frame) -> None:
        *parents, leaf = path.split(".")
        target = message
        for name in parents:
            target = getattr(target, name)
        setattr(target, leaf, value)
    return change


def set_repeated(name: str, values: list[float]) -> Mutation:
    def change(message: pb.Frame) -> None:
        del getattr(message, name)[:]
        getattr(message, name).extend(values)
    return change


def translate(offset: list[float]) -> Mutation:
    def change(message: pb.Frame) -> None:
        if len(message.c2w) == 16:
            for axis, value in enumerate(offset):
                message.c2w[4 * axis + 3] += value
    return change


CAMERA_FIELDS = [f"{camera}.{name}" for camera in ("color_intrinsics", "depth_intrinsics")
                 for name in ("fx", "fy", "cx", "cy")]
MUTATIONS = st.one_of(
    st.tuples(st.sampled_from(CAMERA_FIELDS), FLOATS).map(lambda pair: set_value(*pair)),
    st.tuples(st.sampled_from([f"{c}.{n}" for c in ("color_intrinsics", "depth_intrinsics")
                               for n in ("width", "height")]), SIZES).map(lambda pair: set_value(*pair)),
    st.tuples(st.sampled_from(["c2w", "depth_to_color"]),
              st.lists(FLOATS, min_size=0, max_size=17) | st.just(np.eye(4).reshape(-1).tolist())
              ).map(lambda pair: set_repeated(*pair)),
    st.lists(EDGE_FLOATS | st.floats(-1e4, 1e4), min_size=3, max_size=3).map(translate),
    st.tuples(st.sampled_from(["color.encoding", "depth.encoding"]), st.integers(0, 9)).map(lambda p: set_value(*p)),
    st.tuples(st.sampled_from(["color.data", "depth.data"]), BYTES).map(lambda pair: set_value(*pair)),
    FLOATS.map(lambda scale: set_value("depth.depth_scale", scale)),
    # The whole double range the proto allows (huge, negative, subnormal, nan, inf) and the edges of
    # what a recording's unsigned 64-bit nanoseconds hold: refused with an error ack, never a wedged stream.
    (FLOATS | TIMESTAMP_EDGES).map(lambda seconds: set_value("timestamp", seconds)),
    st.integers(0, 2**64 - 1).map(lambda index: set_value("index", index)),
)


@st.composite
def frames(draw: st.DrawFn) -> pb.Frame:
    """A good frame with a few fields changed, or (now and then) one built from nothing."""
    message = pb.Frame()
    if draw(st.integers(0, 9)):
        message.CopyFrom(draw(st.sampled_from([GOOD, NEXT])))
    for mutation in draw(st.lists(MUTATIONS, min_size=1, max_size=3)):
        mutation(message)
    return message


@st.composite
def render_requests(draw: st.DrawFn) -> pb.RenderRequest:
    request = pb.RenderRequest(c2w=GOOD.c2w, intrinsics=GOOD.color_intrinsics)
    for name in ("fx", "fy", "cx", "cy"):
        if draw(st.booleans()):
            setattr(request.intrinsics, name, draw(FLOATS))
    for name in ("width", "height"):
        if draw(st.booleans()):
            setattr(request.intrinsics, name, draw(SIZES))
    if draw(st.booleans()):
        del request.c2w[:]
        request.c2w.extend(draw(st.lists(FLOATS, max_size=17)))
    elif draw(st.booleans()):
        request.c2w[draw(st.sampled_from([3, 7, 11]))] = draw(EDGE_FLOATS)
    request.outputs.extend(draw(st.lists(st.integers(0, 3), max_size=3)))
    request.color_encoding = draw(st.integers(0, 6))
    request.depth_encoding = draw(st.integers(0, 4))
    request.jpeg_quality = draw(st.integers(0, 2**32 - 1) | st.integers(0, 101))
    return request


CONFIG_KEYS = sorted(flatten(dataclasses.asdict(MapperConfig())))
OVERRIDE_VALUES = (
    st.sampled_from(["-1", "0", "1", "2", "24", "1000000", "1e300", "nan", "inf", "-inf", "0.001", "true", "",
                     "hash", "anchor", "octree", "bogus", str(1 << 70)])
    | st.integers(-10, 100).map(str) | st.floats(allow_nan=True).map(repr) | st.text(max_size=8)
)


@st.composite
def create_requests(draw: st.DrawFn) -> pb.CreateSessionRequest:
    keys = st.sampled_from(CONFIG_KEYS) | st.sampled_from(["model", "nope.key", "", "keyframes..iterations"])
    overrides = draw(st.dictionaries(keys, OVERRIDE_VALUES, max_size=4))
    return pb.CreateSessionRequest(
        preset=draw(st.sampled_from(["", "dense", "sparse", "sparse-fast", "fastest"]) | st.text(max_size=8)),
        overrides=overrides, label=draw(st.text(max_size=40)),
    )


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServerHandle]:
    """Always a local server: a short frame budget keeps a costly accepted config from stalling the test."""
    local = start_local(tmp_path_factory.mktemp("recordings"), "--frame-seconds", "3")
    channel, stub = connect(local.address, timeout=60.0)
    try:
        yield ServerHandle(local.address, channel, stub, local)
    finally:
        channel.close()
        local.stop()


@pytest.fixture(scope="module")
def session(server: ServerHandle) -> SessionRef:
    return SessionRef.from_credentials(server.stub.CreateSession(create_request(TINY, "fuzz"), timeout=CALL_SECONDS))


def call(rpc: Callable[[], object]) -> grpc.StatusCode:
    """The call's status; a hung call (past its timeout) or INTERNAL fails the test."""
    try:
        rpc()
    except grpc.RpcError as error:
        code = error.code()
        assert code != grpc.StatusCode.DEADLINE_EXCEEDED, f"the call hung: {error.details()}"
        assert code != grpc.StatusCode.INTERNAL, f"INTERNAL: {error.details()}"
        return code
    return grpc.StatusCode.OK


def stream(server: ServerHandle, session: SessionRef, messages: list[pb.Frame]) -> list[pb.FrameAck]:
    acks: list[pb.FrameAck] = []
    code = call(lambda: acks.extend(server.stub.StreamFrames(
        iter(messages), metadata=session.stream_metadata(), timeout=CALL_SECONDS)))
    assert code in (grpc.StatusCode.OK, grpc.StatusCode.RESOURCE_EXHAUSTED), code  # the latter: over max_message_bytes
    for ack in acks:
        assert ack.error.code_name != grpc.StatusCode.INTERNAL.name, ack.error.message
    return acks


def assert_still_maps_and_renders(server: ServerHandle, session: SessionRef) -> None:
    (ack,) = stream(server, session, [NEXT])
    assert ack.accepted and not ack.error.code_name, ack
    request = pb.RenderRequest(session_id=session.session_id, c2w=GOOD.c2w, intrinsics=GOOD.color_intrinsics)
    response = server.stub.Render(request, metadata=session.metadata(), timeout=CALL_SECONDS)
    assert response.color.data and response.depth.data


@fuzz(150)
@given(messages=st.lists(frames(), min_size=1, max_size=3))
def test_fuzzed_frames(server: ServerHandle, session: SessionRef, messages: list[pb.Frame]) -> None:
    stream(server, session, messages)


@fuzz(300)
@given(request=render_requests())
def test_fuzzed_renders(server: ServerHandle, session: SessionRef, request: pb.RenderRequest) -> None:
    request.session_id = session.session_id
    call(lambda: server.stub.Render(request, metadata=session.metadata(), timeout=CALL_SECONDS))


@fuzz(60)
@given(request=create_requests())
def test_fuzzed_create_sessions(server: ServerHandle, request: pb.CreateSessionRequest) -> None:
    """An accepted config must also map a frame: no config a client may set breaks its session."""
    created: list[pb.SessionCredentials] = []
    if call(lambda: created.append(server.stub.CreateSession(request, timeout=CALL_SECONDS))) != grpc.StatusCode.OK:
        return
    session = SessionRef.from_credentials(created[0])
    try:
        stream(server, session, [GOOD])
    finally:
        server.stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id), metadata=session.metadata(),
                                 timeout=CALL_SECONDS)


@pytest.mark.parametrize(("preset", "overrides", "named"), [
    ("sparse-fast", {"keyframes.first_iterations": "1000000"}, "config_bounds.max_iterations"),  # hours per frame
    ("dense", {"model.hash_log2_size": "24"}, "config_bounds.max_hash_table_mib"),  # 2 GiB per CreateSession
])
def test_create_session_refuses_configs_beyond_the_bounds(server: ServerHandle, preset: str, overrides: dict,
                                                          named: str) -> None:
    with pytest.raises(grpc.RpcError) as refusal:
        server.stub.CreateSession(pb.CreateSessionRequest(preset=preset, overrides=overrides), timeout=CALL_SECONDS)
    assert refusal.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert refusal.value.details().startswith("overrides: config ") and named in refusal.value.details()


def test_create_session_refuses_options_this_servers_rasterizer_lacks(server: ServerHandle) -> None:
    request = pb.CreateSessionRequest(preset="sparse-fast", overrides={"render.antialiased": "true"})
    with pytest.raises(grpc.RpcError) as refusal:
        server.stub.CreateSession(request, timeout=CALL_SECONDS)
    assert refusal.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert refusal.value.details().startswith("overrides: render.antialiased: gsplat's options only")


def test_restore_refuses_a_snapshot_whose_config_is_beyond_the_bounds(server: ServerHandle) -> None:
    """A crafted 216 KB snapshot once pushed the server to 2.6 GB before anything was checked."""
    data = Mapper(resolve(PRESET, overrides=TINY)).snapshot()
    metadata = read_metadata(data)
    config = json.loads(metadata["config"])
    config["keyframes"]["first_iterations"] = 1000000
    crafted = save_tensors(load_tensors(data), metadata={**metadata, "config": json.dumps(config)})
    with pytest.raises(grpc.RpcError) as refusal:
        server.stub.RestoreSession(iter([pb.RestoreChunk(data=crafted)]), timeout=CALL_SECONDS)
    assert refusal.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert refusal.value.details().startswith("data: ") and "config_bounds.max_iterations" in refusal.value.details()


def test_the_session_still_maps_and_renders(server: ServerHandle, session: SessionRef) -> None:
    assert_still_maps_and_renders(server, session)


def test_frame_numbers_up_to_uint64_max_are_mapped_and_checkpointed(tmp_path) -> None:
    """A frame numbered 2^64 - 1 once made the checkpoint after it fail and stopped its session's mapping."""
    local = start_local(tmp_path, "--checkpoint-interval", "1")
    channel, stub = connect(local.address, timeout=60.0)
    try:
        server = ServerHandle(local.address, channel, stub, local)
        session = SessionRef.from_credentials(stub.CreateSession(create_request(TINY, "uint64"), timeout=CALL_SECONDS))
        largest = pb.Frame()
        largest.CopyFrom(GOOD)
        largest.index = 2**64 - 1
        (ack,) = stream(server, session, [largest])
        assert ack.accepted and ack.index == 2**64 - 1, ack
        assert_still_maps_and_renders(server, session)
        assert list(tmp_path.rglob("*checkpoint*")), "the checkpoints were written"
    finally:
        channel.close()
        local.stop()
