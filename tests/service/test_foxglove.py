"""The live view: a Foxglove WebSocket client sees a session's render, trajectory and map, and the
recording carries the keyframes' render and map under the same schemas."""

from __future__ import annotations

import asyncio
import logging
import ssl
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
from ogapi import recording
from ogapi.v1 import mapping_pb2 as pb
from ogclient.connection import SessionRef, Transport, connect
from ogclient.streaming import StreamResult, stream_frames
from ogserver import apikeys
from ogserver.live.channels import session_prefix
from ogserver.live.port_access import port_access
from ogserver.live.publisher import LIVE_TOPICS, REFINED_TOPICS
from ogserver.live.views import TOPIC_REFINED_TRAJECTORY, TOPIC_TRAJECTORY
from ogserver.settings import load

from .certificates import make_ca
from .inprocess import serving, settings
from .scene import FROZEN, TINY, create_request, messages, scene

pytest.importorskip("foxglove", reason="the live extra (foxglove-sdk) is not installed")
foxglove_client = pytest.importorskip("tests.service.foxglove_client", reason="websockets is not installed")

MAX_POINTS = 400


def wait_for(condition, seconds: float = 10.0) -> None:
    deadline = time.monotonic() + seconds
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.05)


def live_settings(tmp_path):
    configured = settings(tmp_path)
    configured.live.foxglove_port = 0
    configured.live.view_seconds = 0.2
    configured.live.view_points = MAX_POINTS
    return configured


def watch_while_streaming(running, session: SessionRef, url: str, topics: list[str], frames,
                          acks: StreamResult | None = None):
    """What a client at ``url`` receives of the session's ``topics`` while ``frames`` are streamed (their
    acks into ``acks``, when given)."""
    fox, prefix = running.server.live.foxglove, session_prefix(session.session_id)

    async def watch():
        watcher = asyncio.create_task(foxglove_client.watch(url, prefix, topics, {prefix + t for t in topics}, 30))
        # Stream once the client has subscribed to every topic of the session.
        await asyncio.to_thread(wait_for, lambda: all(fox.wants(prefix + topic) for topic in topics))
        await asyncio.to_thread(stream_frames, running.stub, session, frames, None, False, acks)
        return await watcher

    return asyncio.run(watch())


def test_foxglove_client_sees_render_transform_and_point_cloud(tmp_path) -> None:
    frames = messages(scene())
    configured = live_settings(tmp_path)
    with serving(configured) as running:
        credentials = running.stub.CreateSession(create_request(TINY))
        session = SessionRef.from_credentials(credentials)
        prefix = session_prefix(session.session_id)
        url = f"ws://127.0.0.1:{running.server.live.foxglove.port}"
        received = watch_while_streaming(running, session, url, list(LIVE_TOPICS), frames)
        running.stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id), metadata=session.metadata())

    poses = {tuple(np.round(np.array(frame.c2w).reshape(4, 4)[:3, 3], 6)) for frame in frames}
    transforms = [message for _, message in received.messages[prefix + recording.TOPIC_TRANSFORM]]
    assert received.channels[prefix + recording.TOPIC_TRANSFORM].schema_name == "foxglove.FrameTransform"
    for transform in transforms:
        assert transform.parent_frame_id == f"{session.session_id}/world"
        assert transform.child_frame_id == f"{session.session_id}/camera"
        assert tuple(np.round([transform.translation.x, transform.translation.y, transform.translation.z], 6)) in poses

    _, path = received.messages[prefix + TOPIC_TRAJECTORY][-1]
    sent = [tuple(np.array(frame.c2w).reshape(4, 4)[:3, 3]) for frame in frames]
    assert path.poses and path_positions(path) == sent[: len(path.poses)]

    width, height = frames[0].color_intrinsics.width, frames[0].color_intrinsics.height
    _, render = received.messages[prefix + recording.TOPIC_RENDER][-1]
    assert received.channels[prefix + recording.TOPIC_RENDER].schema_name == "foxglove.CompressedImage"
    assert render.format == "jpeg"
    image = cv2.imdecode(np.frombuffer(render.data, np.uint8), cv2.IMREAD_COLOR)
    assert image.shape == (height, width, 3) and image.std() > 1.0, "the render is blank"
    _, color = received.messages[prefix + recording.TOPIC_COLOR][-1]
    assert color.data in {frame.color.data for frame in frames}, "the input image is not one that was sent"

    assert received.channels[prefix + recording.TOPIC_MAP].schema_name == "foxglove.PointCloud"
    _, cloud = received.messages[prefix + recording.TOPIC_MAP][-1]
    points = decode_points(cloud)
    assert 0 < len(points) <= MAX_POINTS and np.isfinite(points["xyz"]).all()
    assert cloud.frame_id == f"{session.session_id}/world"

    # The recording: the keyframes' render and map under the same schemas, readable as before.
    path = Path(configured.record_dir) / credentials.recording
    recorded = recording.load(path)
    assert len(recorded.frames) == len(frames)
    schemas = {item.topic: item.schema for item in recording.read_messages(path)}
    assert schemas[recording.TOPIC_RENDER] == "foxglove.CompressedImage"
    assert schemas[recording.TOPIC_MAP] == "foxglove.PointCloud"
    repaired = tmp_path / "repaired.mcap"
    recording.repair(path, repaired)
    maps = list(recording.read_messages(repaired, {recording.TOPIC_MAP}))
    assert maps and all(0 < len(decode_points(type(cloud).FromString(item.data))) <= MAX_POINTS for item in maps)


def path_positions(message) -> list[tuple[float, float, float]]:
    return [(pose.position.x, pose.position.y, pose.position.z) for pose in message.poses]


def test_a_refining_session_shows_both_trajectories(tmp_path) -> None:
    frames = messages(scene())
    refine = {**TINY, "poses.refine": "true", "poses.translation_lr": "0.01"}
    with serving(live_settings(tmp_path)) as running:
        session = SessionRef.from_credentials(running.stub.CreateSession(create_request(refine)))
        prefix = session_prefix(session.session_id)
        url = f"ws://127.0.0.1:{running.server.live.foxglove.port}"
        acks = StreamResult()
        topics = [TOPIC_TRAJECTORY, *REFINED_TOPICS]
        received = watch_while_streaming(running, session, url, topics, frames, acks)
        running.stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id), metadata=session.metadata())

    client = [tuple(np.array(frame.c2w).reshape(4, 4)[:3, 3]) for frame in frames]
    refined = [tuple(np.array(ack.pose_correction.refined_c2w).reshape(4, 4)[:3, 3]) for ack in acks.acks]
    assert client != refined, "refinement moved no pose"
    for topic, poses in ((TOPIC_TRAJECTORY, client), (TOPIC_REFINED_TRAJECTORY, refined)):
        assert received.channels[prefix + topic].schema_name == "foxglove.PosesInFrame"
        _, path = received.messages[prefix + topic][-1]
        assert path.frame_id == f"{session.session_id}/world"
        shown = path_positions(path)
        assert shown and shown == poses[: len(shown)], "the path is not the session's poses so far, in order"
    transforms = [message for _, message in received.messages[prefix + recording.TOPIC_REFINED_TRANSFORM]]
    assert transforms and all(transform.child_frame_id == f"{session.session_id}/camera_refined"
                              for transform in transforms)
    assert {(t.translation.x, t.translation.y, t.translation.z) for t in transforms} <= set(refined)


def decode_points(cloud) -> np.ndarray:
    """Points by the cloud's own field table: x, y, z float32, then RGBA bytes."""
    offsets = {field.name: field.offset for field in cloud.fields}
    assert cloud.point_stride == 16 and offsets == {"x": 0, "y": 4, "z": 8, "red": 12, "green": 13, "blue": 14,
                                                    "alpha": 15}
    return np.frombuffer(cloud.data, dtype=[("xyz", "<f4", 3), ("rgba", "u1", 4)])


def test_without_the_port_no_foxglove_server_starts(tmp_path) -> None:
    with serving(settings(tmp_path)) as running:
        assert running.server.live is not None and running.server.live.foxglove is None


# ---------------------------------------------------------------------------- who may connect

def session_topics(session_id: str) -> set[str]:
    return {session_prefix(session_id) + topic for topic in LIVE_TOPICS}


def shown(url: str, until=lambda topics: False, seconds: float = 20.0, tls: ssl.SSLContext | None = None) -> set[str]:
    """The topics advertised to a client at ``url``."""
    return set(asyncio.run(foxglove_client.topics(url, until, seconds, tls=tls)))


def test_each_credential_is_shown_only_the_sessions_it_sees(tmp_path) -> None:
    """The web view's credentials, with its owners: an API key sees its own sessions, a session token its one
    session, the operator's Foxglove token every session; a wrong key is refused and counted."""
    configured = live_settings(tmp_path)
    configured.access.api_keys = {"alice": apikeys.digest("alice-key"), "bob": apikeys.digest("bob-key")}
    configured.access.max_auth_failures = 2
    token_file = tmp_path / "foxglove.token"
    token_file.write_text("a-secret-of-twenty-four-chars\n")
    configured.live.foxglove_token_file = str(token_file)
    frames = messages(scene())[:4]
    with serving(configured) as running:
        fox = running.server.live.foxglove
        base = f"ws://127.0.0.1:{fox.port}/"

        def create(key: str) -> SessionRef:
            return SessionRef.from_credentials(running.stub.CreateSession(create_request(FROZEN),
                                                                          metadata=(("x-api-key", key),)))

        alice, bob = create("alice-key"), create("bob-key")
        mine, theirs = session_topics(alice.session_id), session_topics(bob.session_id)
        assert shown(base + "?token=a-secret-of-twenty-four-chars", lambda topics: mine | theirs <= topics) >= \
            mine | theirs, "the operator's token sees every session"
        assert shown(base + "?key=alice-key", lambda topics: mine <= topics) == mine
        assert shown(base + "?key=bob-key", lambda topics: theirs <= topics) == theirs
        assert shown(f"{base}?token={alice.token}", lambda topics: mine <= topics) == mine

        for url in (base, base + "?token=a-secret-of-twenty-four-charX"):
            assert asyncio.run(foxglove_client.first_message(url)) == 401
        failures = fox.gate.viewers.failures
        assert len(failures) == 1, "the wrong token was counted against its address"
        assert asyncio.run(foxglove_client.first_message(base + "?key=mallory-key")) == 401
        assert asyncio.run(foxglove_client.first_message(base + "?key=mallory-key")) == 429, "past the limit"
        assert asyncio.run(foxglove_client.first_message(base + "?key=alice-key")) == "serverInfo"

        # A session opened later by another owner is never shown: alice sees her new one, not bob's.
        async def later() -> tuple[dict[str, int], SessionRef]:
            async def open_both() -> SessionRef:
                await asyncio.sleep(1.0)
                await asyncio.to_thread(create, "bob-key")
                return await asyncio.to_thread(create, "alice-key")

            opening = asyncio.create_task(open_both())
            seen = await foxglove_client.topics(base + "?key=alice-key", lambda topics: len(topics) >= 2 * len(mine))
            return seen, await opening

        seen, newer = asyncio.run(later())
        assert set(seen) == mine | session_topics(newer.session_id)

        # A subscription to a channel the caller was not shown never reaches the server.
        theirs_by_topic = asyncio.run(foxglove_client.topics(base + "?key=bob-key", lambda topics: theirs <= topics))
        hidden, own = (theirs_by_topic[session_prefix(bob.session_id) + recording.TOPIC_COLOR],
                       asyncio.run(foxglove_client.topics(base + "?key=alice-key", lambda topics: mine <= topics))
                       [session_prefix(alice.session_id) + recording.TOPIC_COLOR])

        def subscribed() -> tuple[bool, bool]:
            wait_for(lambda: fox.wants(session_prefix(alice.session_id) + recording.TOPIC_COLOR))
            return fox.wants(session_prefix(bob.session_id) + recording.TOPIC_COLOR), True

        async def subscribe_and_stream() -> tuple[foxglove_client.Answers, object]:
            def check() -> tuple[bool, bool]:
                wanted = subscribed()
                stream_frames(running.stub, bob, frames, None, False, None)
                return wanted

            return await foxglove_client.subscribe_then(base + "?key=alice-key", [hidden, own], {own}, check,
                                                      listen=2.0)

        answers, (hidden_wanted, _) = asyncio.run(subscribe_and_stream())
        assert not hidden_wanted, "the hidden channel's subscription reached the SDK"
        assert f"Unknown channel ID: {hidden}" in answers.statuses
        assert answers.data_frames == 0, "bob's frames reached alice"


def test_an_open_server_shows_every_session(tmp_path) -> None:
    with serving(live_settings(tmp_path)) as running:
        ids = [running.stub.CreateSession(create_request(FROZEN)).session_id for _ in range(2)]
        every = session_topics(ids[0]) | session_topics(ids[1])
        url = f"ws://127.0.0.1:{running.server.live.foxglove.port}"
        assert shown(url, lambda topics: every <= topics) == every


def test_under_mutual_tls_the_certificate_names_the_owner(tmp_path) -> None:
    ca = make_ca(tmp_path / "pki", clients=("alice", "bob"))
    configured = live_settings(tmp_path)
    ca.serve(configured.access, mutual=True)
    with serving(configured) as running:
        def client(name: str | None) -> ssl.SSLContext:
            trusting = ssl.create_default_context(cafile=str(ca.ca))
            if name:
                trusting.load_cert_chain(str(ca.clients[name].cert), str(ca.clients[name].key))
            return trusting

        opened = {}
        for name in ("alice", "bob"):
            pem = ca.clients[name]
            channel, stub = connect(running.address, 10, Transport(ca=str(ca.ca), cert=str(pem.cert), key=str(pem.key)))
            with channel:
                opened[name] = session_topics(stub.CreateSession(create_request(FROZEN)).session_id)
        url = f"wss://127.0.0.1:{running.server.live.foxglove.port}"
        for name in ("alice", "bob"):
            assert shown(url, lambda topics, name=name: opened[name] <= topics, tls=client(name)) == opened[name]
        with pytest.raises(Exception):  # noqa: B017 (no certificate: the TLS handshake fails, however it shows)
            asyncio.run(foxglove_client.first_message(url, tls=client(None)))


def test_a_foreign_origin_is_refused(tmp_path) -> None:
    """A web page on another origin cannot read the port, even where no token is asked."""
    configured = live_settings(tmp_path)
    configured.live.foxglove_origins = ["https://app.foxglove.dev"]
    with serving(configured) as running:
        url = f"ws://127.0.0.1:{running.server.live.foxglove.port}"
        assert asyncio.run(foxglove_client.first_message(url, origin="https://evil.example")) == 403
        assert asyncio.run(foxglove_client.first_message(url, origin="null")) == 403
        assert asyncio.run(foxglove_client.first_message(url, origin="https://app.foxglove.dev")) == "serverInfo"
        assert asyncio.run(foxglove_client.first_message(url)) == "serverInfo"  # a native client sends no Origin


def test_the_port_speaks_tls_when_grpc_does(tmp_path) -> None:
    ca = make_ca(tmp_path / "pki")
    configured = live_settings(tmp_path)
    ca.serve(configured.access)
    with serving(configured) as running:
        fox = running.server.live.foxglove
        assert fox.tls
        trusting = ssl.create_default_context(cafile=str(ca.ca))
        url = f"wss://127.0.0.1:{fox.port}/"
        assert asyncio.run(foxglove_client.first_message(url, tls=trusting)) == "serverInfo"  # open: no credential
        assert asyncio.run(foxglove_client.first_message(url + "?token=not-a-session-token", tls=trusting)) == 401
        with pytest.raises(Exception):  # noqa: B017 (whatever a plain client makes of a TLS answer)
            asyncio.run(foxglove_client.first_message(f"ws://127.0.0.1:{fox.port}/"))


class Lines(logging.Handler):
    """What reaches the root logger's handlers: the server's log."""

    def __init__(self) -> None:
        super().__init__(logging.INFO)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def test_bad_subscribes_leave_a_bounded_log(tmp_path) -> None:
    """2 000 subscriptions to a channel never shown: each answered as the SDK answers one, none logged."""
    root, log = logging.getLogger(), Lines()
    root.addHandler(log)
    try:
        with serving(live_settings(tmp_path)) as running:
            url = f"ws://127.0.0.1:{running.server.live.foxglove.port}"
            statuses = asyncio.run(foxglove_client.subscribe_unknown(url, messages=10, entries=200))
    finally:
        root.removeHandler(log)
    assert statuses == 2000
    lines = [record for record in log.records if "unknown channel" in record.getMessage().lower()]
    assert len(lines) <= 2, f"{len(lines)} lines, from {sorted({record.name for record in lines})}"
    assert sum(len(record.getMessage()) for record in log.records) < 20_000


def test_bad_origins_and_tokens_are_refused_in_one_line(tmp_path) -> None:
    refused = r"live\.foxglove_origins\[0\] must be an origin such as https://app\.foxglove\.dev"
    with pytest.raises(ValueError, match=refused):
        load(None, {"foxglove_origins": ["app.foxglove.dev"]})
    configured = live_settings(tmp_path)
    short = tmp_path / "short.token"
    short.write_text("guessable\n")
    configured.live.foxglove_token_file = str(short)
    with pytest.raises(ValueError, match=r"short\.token must hold one token of 16 to 256"):
        port_access(configured)
    configured.live.foxglove_token_file = str(tmp_path / "missing.token")
    with pytest.raises(ValueError, match=r"live\.foxglove_token_file: cannot read"):
        port_access(configured)
