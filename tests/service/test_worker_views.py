"""The live views of a server whose sessions map in worker processes (``--workers``): the web view answers
as a threaded server's does, the Foxglove view publishes a session's poses, render and map, and a worker
killed shows its sessions as gone in both views while the server and the other worker's sessions go on.
Without the live extra (foxglove-sdk) the module is skipped, as ``test_foxglove.py`` is."""

from __future__ import annotations

import json
import os
import signal
import time
import urllib.error
import urllib.request
from collections.abc import Iterator

import cv2
import numpy as np
import pytest
from ogapi import recording
from ogclient.connection import SessionRef
from ogclient.streaming import stream_frames
from ogserver.errors import ServiceError
from ogserver.live.channels import session_prefix
from ogserver.web.catalogue import Credential
from ogserver.web.http_server import Pages

from .inprocess import Running, serving, settings
from .scene import FROZEN, create_request, messages, scene
from .test_foxglove import MAX_POINTS, decode_points, session_topics, shown, wait_for, watch_while_streaming

FRAMES = "0:6"  # 5 streamed, a few keyframes
VOLATILE = ("processing_fps",)  # rates: not the same in two runs


def view_settings(tmp_path, workers: int):
    """Both views on; the web view renders the newest keyframe itself (no recorded views to wait for)."""
    configured = settings(tmp_path)
    configured.workers = workers
    configured.live.web_port = 0
    configured.live.web_seconds = 0.1
    configured.live.foxglove_port = 0
    configured.live.view_seconds = 0.2
    configured.live.view_points = MAX_POINTS
    configured.live.record_views = False
    return configured


@pytest.fixture(scope="module")
def threads(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Running]:
    with serving(view_settings(tmp_path_factory.mktemp("threads"), 0)) as running:
        yield running


@pytest.fixture(scope="module")
def one_worker(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Running]:
    with serving(view_settings(tmp_path_factory.mktemp("one-worker"), 1)) as running:
        yield running


@pytest.fixture(scope="module")
def workers(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Running]:
    with serving(view_settings(tmp_path_factory.mktemp("workers"), 2)) as running:
        yield running


def get(url: str) -> tuple[int, str, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=30) as response:
            return response.status, response.headers.get("Content-Type", ""), response.read()
    except urllib.error.HTTPError as error:
        return error.code, error.headers.get("Content-Type", ""), error.read()


def mapped(running: Running, label: str, frames: str = FRAMES) -> SessionRef:
    session = SessionRef.from_credentials(running.stub.CreateSession(create_request(FROZEN, label)))
    stream_frames(running.stub, session, messages(scene(frames)), None, False)
    return session


def web_answers(running: Running, session: SessionRef) -> dict[str, tuple[int, str, bytes]]:
    """What the web view answers for a session, by path (the Gaussians before the state, which counts them)."""
    base, query = f"http://127.0.0.1:{running.server.web.port}", f"?token={session.token}"
    paths = ["/", f"/map/{session.session_id}", f"/api/map/{session.session_id}/splats.ply",
             f"/api/map/{session.session_id}/state", f"/api/map/{session.session_id}/frame",
             f"/api/map/{session.session_id}/render.jpg", "/api/map/nosuchmap/state"]
    return {path.replace(session.session_id, "ID"): get(base + path + query) for path in paths}


def ply_table(data: bytes) -> np.ndarray:
    header, _, body = data.partition(b"end_header\n")
    return np.frombuffer(body, np.float32).reshape(-1, header.count(b"property float"))


def state(body: bytes, session: SessionRef) -> dict:
    value = json.loads(body)
    assert value.pop("id") == session.session_id
    for key in VOLATILE:
        value["stats"].pop(key)
    return value


@pytest.mark.parametrize("server", ["one_worker", "workers"])
def test_the_web_view_answers_as_a_threaded_servers(threads: Running, server: str, request) -> None:
    running: Running = request.getfixturevalue(server)
    ours, theirs = mapped(threads, "room"), mapped(running, "room")
    expected, answered = web_answers(threads, ours), web_answers(running, theirs)
    assert {path: answer[:2] for path, answer in answered.items()} == \
        {path: answer[:2] for path, answer in expected.items()}, "statuses and content types"
    assert all(answer[0] == 200 for path, answer in answered.items() if "nosuchmap" not in path)
    assert theirs.session_id.encode() in answered["/"][2]
    assert answered["/map/ID"][2] == expected["/map/ID"][2]
    assert state(answered["/api/map/ID/state"][2], theirs) == state(expected["/api/map/ID/state"][2], ours)
    assert answered["/api/map/ID/frame"][2] == expected["/api/map/ID/frame"][2], "the keyframe's input image"
    splats, reference = (ply_table(answers["/api/map/ID/splats.ply"][2]) for answers in (answered, expected))
    assert splats.shape == reference.shape and len(splats) > 0
    assert np.allclose(splats, reference, atol=1e-4)
    render, reference_render = (cv2.imdecode(np.frombuffer(answers["/api/map/ID/render.jpg"][2], np.uint8),
                                             cv2.IMREAD_COLOR) for answers in (answered, expected))
    assert render.shape == reference_render.shape and render.std() > 1.0
    assert np.abs(render.astype(float) - reference_render).mean() < 2.0


def test_the_foxglove_view_publishes_a_workers_session(workers: Running) -> None:
    session = SessionRef.from_credentials(workers.stub.CreateSession(create_request(FROZEN, "watched")))
    prefix, frames = session_prefix(session.session_id), messages(scene(FRAMES))
    url = f"ws://127.0.0.1:{workers.server.live.foxglove.port}"
    topics = [recording.TOPIC_TRANSFORM, recording.TOPIC_RENDER, recording.TOPIC_MAP]
    received = watch_while_streaming(workers, session, url, topics, frames)
    sent = {tuple(np.round(np.array(frame.c2w).reshape(4, 4)[:3, 3], 6)) for frame in frames}
    transforms = [message for _, message in received.messages[prefix + recording.TOPIC_TRANSFORM]]
    assert transforms and {tuple(np.round([t.translation.x, t.translation.y, t.translation.z], 6))
                           for t in transforms} <= sent
    _, render = received.messages[prefix + recording.TOPIC_RENDER][-1]
    image = cv2.imdecode(np.frombuffer(render.data, np.uint8), cv2.IMREAD_COLOR)
    width, height = frames[0].color_intrinsics.width, frames[0].color_intrinsics.height
    assert image.shape == (height, width, 3) and image.std() > 1.0
    _, cloud = received.messages[prefix + recording.TOPIC_MAP][-1]
    assert 0 < len(decode_points(cloud)) <= MAX_POINTS and cloud.frame_id == f"{session.session_id}/world"


def worker_of(running: Running, session: SessionRef):
    return next(item.worker for item in running.server.registry.sessions() if item.id == session.session_id)


def test_a_killed_workers_sessions_are_gone_from_both_views(workers: Running) -> None:
    """Last in the module: it leaves the server one worker."""
    lost, kept = mapped(workers, "lost", "0:3"), mapped(workers, "kept", "0:3")
    worker = worker_of(workers, lost)
    assert worker is not worker_of(workers, kept), "both sessions on one worker"
    catalogue = workers.server.web.catalogue
    held = catalogue.find(lost.session_id, Credential())  # a request under way while the worker dies
    base, fox = f"http://127.0.0.1:{workers.server.web.port}", f"ws://127.0.0.1:{workers.server.live.foxglove.port}"
    assert session_topics(lost.session_id) <= shown(fox, lambda topics: session_topics(lost.session_id) <= topics)

    os.kill(worker.pid, signal.SIGKILL)
    wait_for(lambda: worker.lost is not None)
    with pytest.raises(ServiceError) as gone:
        held.state()
    assert "worker process that held the session stopped (killed by SIGKILL)" in gone.value.message

    class Stale:  # a catalogue that found the session just before its worker died
        busy = catalogue.busy

        def find(self, map_id: str, credential: Credential):
            return held

    answer = Pages(Stale()).answer(f"/api/map/{lost.session_id}/state", {}, [], "127.0.0.1")
    assert answer.status == 404 and answer.body.startswith(b"the map is gone: the worker process")
    status, _, index = get(f"{base}/")
    assert status == 200 and lost.session_id.encode() not in index and kept.session_id.encode() in index
    for part in ("state", "splats.ply", "frame", "render.jpg"):
        assert get(f"{base}/api/map/{lost.session_id}/{part}")[0] == 404, part
        assert get(f"{base}/api/map/{kept.session_id}/{part}")[0] == 200, part
    time.sleep(3 * workers.server.live.settings.view_seconds)  # the Foxglove view looks again meanwhile
    topics = shown(fox, lambda topics: session_topics(kept.session_id) <= topics)
    assert session_topics(kept.session_id) <= topics and not session_topics(lost.session_id) & topics
    assert len(stream_frames(workers.stub, kept, messages(scene("3:5")), None, False).mapped) == 2  # mapping goes on
