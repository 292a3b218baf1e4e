"""The web view in a real browser: a session's map drawn by Spark from a pose agrees with the server's own
render from it, and follows the map as more frames arrive; callers see only what gRPC lets them see.
``ogserver view`` serves one snapshot's or recording's map, and ``ogclient view`` runs it as a child."""

from __future__ import annotations

import http.client
import json
import os
import signal
import ssl
import subprocess
import sys
import time
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
from ogapi import API_KEY_METADATA_KEY
from ogapi.v1 import mapping_pb2 as pb
from ogclient.connection import SessionRef, Transport, connect
from ogclient.evaluation import render, snapshot_bytes
from ogclient.streaming import stream_frames
from ogserver import apikeys, view
from ogserver.settings import load
from ogserver.web import still
from ogserver.web.catalogue import Credential
from ogserver.web.hosts import is_loopback
from ogserver.web.maps import MapView

from ogmapping.frames.camera import Intrinsics

from .browser import PAGE_SECONDS, browser, fragment, needs_browser, psnr
from .certificates import make_ca
from .inprocess import serving, settings
from .scene import FROZEN, TINY, create_request, messages, scene

MIN_PSNR = 25.0
STOP_SECONDS = 5  # a stopped view is gone this soon
PATH = os.pathsep.join(sys.path)  # this process's packages for the ogclient it starts


def web_settings(tmp_path):
    configured = settings(tmp_path)
    configured.live.web_port = 0
    configured.live.web_seconds = 0.1
    return configured


def pose_and_camera(frame: pb.Frame) -> tuple[np.ndarray, Intrinsics]:
    k = frame.color_intrinsics
    return np.array(frame.c2w).reshape(4, 4), Intrinsics(k.fx, k.fy, k.cx, k.cy, k.width, k.height)


def screenshot(page) -> np.ndarray:
    png = page.locator("#view").screenshot()
    return cv2.cvtColor(cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB) / 255.0


@needs_browser
def test_page_at_a_pose_agrees_with_the_render_and_follows_the_map(tmp_path) -> None:
    frames = messages(scene())
    with serving(web_settings(tmp_path)) as running, browser() as chromium:
        session = SessionRef.from_credentials(running.stub.CreateSession(create_request(TINY)))
        stream_frames(running.stub, session, frames[:4], None, False)
        c2w, camera = pose_and_camera(frames[3])
        url = f"http://127.0.0.1:{running.server.web.port}/map/{session.session_id}?token={session.token}"
        page = chromium.new_page()
        page.goto(url + fragment(c2w, camera))
        page.wait_for_function("window.ogmapReady === true || window.ogmapError", timeout=PAGE_SECONDS * 1000)
        assert page.evaluate("window.ogmapError") is None
        first_version = page.evaluate("window.ogmapVersion")
        drawn = screenshot(page)
        expected = render(running.stub, session, c2w, camera).color
        assert drawn.shape == expected.shape
        agreement = psnr(drawn, expected)
        assert agreement >= MIN_PSNR, f"PSNR {agreement:.2f} dB"

        stream_frames(running.stub, session, frames[4:], None, False)
        page.wait_for_function(f"window.ogmapVersion > {first_version}", timeout=PAGE_SECONDS * 1000)
        time.sleep(0.5)  # the newest version's frame drawn
        later = screenshot(page)
        assert psnr(later, render(running.stub, session, c2w, camera).color) >= MIN_PSNR
        assert psnr(later, drawn) < 60  # the map changed, and so did the page

        errors: list[str] = []
        free = chromium.new_page(viewport={"width": 640, "height": 360})
        free.on("pageerror", lambda error: errors.append(str(error)))
        free.goto(url)
        free.wait_for_function("document.querySelectorAll('#stats dt').length > 0 && "
                               "document.getElementById('render').naturalWidth > 0", timeout=PAGE_SECONDS * 1000)
        assert errors == []


def get(url: str) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=30) as response:
            return response.status, response.read()
    except urllib.error.HTTPError as error:
        return error.code, error.read()


def test_with_api_keys_a_caller_sees_only_its_own_sessions(tmp_path) -> None:
    configured = web_settings(tmp_path)
    configured.access.api_keys = {"alice": apikeys.digest("alice-key"), "bob": apikeys.digest("bob-key")}
    with serving(configured) as running:
        alice = SessionRef.from_credentials(running.stub.CreateSession(create_request(FROZEN, "alice-room"),
                                                                       metadata=[(API_KEY_METADATA_KEY, "alice-key")]))
        bob = SessionRef.from_credentials(running.stub.CreateSession(create_request(FROZEN, "bob-room"),
                                                                     metadata=[(API_KEY_METADATA_KEY, "bob-key")]))
        frames = messages(scene("0:2"))
        stream_frames(running.stub, alice, frames, None, False)
        base = f"http://127.0.0.1:{running.server.web.port}"
        alice_id = alice.session_id
        paths = ["/", f"/map/{alice_id}", f"/api/map/{alice_id}/state", f"/api/map/{alice_id}/splats.ply",
                 f"/api/map/{alice_id}/frame", f"/api/map/{alice_id}/render.jpg"]
        for query in ("", "?key=wrong-key", "?token=wrong-token", "?key=bob-key", f"?token={bob.token}"):
            for path in paths:
                status, body = get(base + path + query)
                assert alice_id.encode() not in body and b"alice-room" not in body, (path, query)
                if path != "/" or query in ("", "?key=wrong-key", "?token=wrong-token"):
                    assert status in (401, 404), (path, query, status)
        status, index = get(f"{base}/?key=bob-key")
        assert status == 200 and bob.session_id.encode() in index
        for query in ("?key=alice-key", f"?token={alice.token}"):
            status, index = get(f"{base}/{query}")
            assert status == 200 and alice_id.encode() in index and bob.session_id.encode() not in index
            for path in paths[1:]:
                assert get(base + path + query)[0] == 200, (path, query)
        status, state = get(f"{base}/api/map/{alice_id}/state?key=alice-key")
        assert json.loads(state)["stats"]["mapped"] == len(frames)
        assert get(f"{base}/api/map/{alice_id}/splats.ply?key=alice-key&center=1,2")[0] == 400
        busy = running.server.web.catalogue.busy  # the decodes and renders, and the requests' CPU, counted
        assert busy.count >= 1 and busy.seconds > 0 and busy.cpu_seconds > 0


def test_loopback_addresses() -> None:
    assert all(map(is_loopback, ("127.0.0.1", "127.3.2.1", "::1", "[::1]", "localhost")))
    assert not any(map(is_loopback, ("0.0.0.0", "::", "10.0.0.1", "example.org")))


def test_the_web_view_answers_only_requests_naming_its_hosts(tmp_path) -> None:
    configured = web_settings(tmp_path)
    configured.live.web_hosts = ["maps.example.org"]
    with serving(configured) as running:
        session = running.stub.CreateSession(create_request(FROZEN)).session_id
        url = f"http://127.0.0.1:{running.server.web.port}/"
        for host in ("maps.example.org:80", "localhost", "127.0.0.1"):
            with urllib.request.urlopen(urllib.request.Request(url, headers={"Host": host}), timeout=30) as response:
                assert session.encode() in response.read(), host
        for path in ("", f"api/map/{session}/state"):
            request = urllib.request.Request(url + path, headers={"Host": "attacker.example:80"})
            with pytest.raises(urllib.error.HTTPError) as refused:
                urllib.request.urlopen(request, timeout=30)
            assert refused.value.code == 403 and session.encode() not in refused.value.read()


@dataclass(frozen=True)
class Room:
    """A small map as a snapshot and as a recording (no snapshot beside it), and the server's render of it."""

    snapshot: Path
    recording: Path
    c2w: np.ndarray
    camera: Intrinsics
    expected: np.ndarray
    path: np.ndarray  # the session's keyframes' positions (n, 3)


@pytest.fixture(scope="module")
def room(tmp_path_factory: pytest.TempPathFactory) -> Room:
    tmp_path = tmp_path_factory.mktemp("room")
    frames = messages(scene())
    with serving(web_settings(tmp_path)) as running:
        session = SessionRef.from_credentials(running.stub.CreateSession(create_request(TINY)))
        stream_frames(running.stub, session, frames[:4], None, False)
        c2w, camera = pose_and_camera(frames[3])
        expected = render(running.stub, session, c2w, camera).color
        path = np.array(running.server.web.catalogue.visible(Credential(token=session.token))[0].state()["path"])
        snapshot = tmp_path / "room.safetensors"
        snapshot.write_bytes(snapshot_bytes(running.stub, session))
        closed = running.stub.CloseSession(pb.CloseSessionRequest(session_id=session.session_id),
                                           metadata=session.metadata())
        return Room(snapshot, running.record_dir / closed.recording, c2w, camera, expected, path)


def start(*command: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", *command, "--device", "cpu"], stdout=subprocess.PIPE, text=True,
                            env={**os.environ, "PYTHONPATH": PATH})


def test_a_recordings_map_is_the_map_a_replay_builds(room: Room) -> None:
    said: list[str] = []
    replayed = still.open_map(room.recording, "cpu", said.append)
    assert said == [f"mapping the 4 recorded frames of {room.recording.name} here (a snapshot beside it, "
                    f"{room.recording.stem}.safetensors, would be read instead)"]
    assert replayed.mapper.stats().frames == 4
    assert psnr(replayed.mapper.render(room.c2w, room.camera).color, room.expected) >= 40


def test_a_snapshots_and_a_recordings_page_shows_the_sessions_keyframes_path(room: Room) -> None:
    assert len(room.path) >= 2
    for path in (room.snapshot, room.recording):
        state = MapView(still.open_map(path, "cpu", lambda _: None), 0.0).state()
        assert state["stats"]["keyframes"] == len(room.path), path.name
        assert np.allclose(state["path"], room.path, atol=1e-4), path.name
        assert np.dot(state["up"], [0, 0, 1]) > 0.99, path.name  # the synthetic room's z
        assert np.allclose(np.reshape(state["start"], (4, 4))[:3, 3], state["path"][-1], atol=1e-4), path.name


def test_ogserver_view_serves_the_map_page_on_loopback_until_sigterm(room: Room) -> None:
    process = start("ogserver", "view", str(room.snapshot))
    try:
        line = process.stdout.readline()
        assert line.startswith(f"{view.READY_PREFIX} http://127.0.0.1:"), line
        url = line[len(view.READY_PREFIX):].strip()
        status, page = get(url)
        assert status == 200 and b"<html" in page.lower()
        assert get(url.split("?")[0])[0] == 401
        process.send_signal(signal.SIGTERM)
        assert process.wait(STOP_SECONDS) == 0
    finally:
        process.kill()
        process.wait()


def test_ogclient_view_forwards_progress_and_stops_its_server_with_it(room: Room) -> None:
    process = start("ogclient", "view", str(room.recording))
    try:
        assert process.stdout.readline().startswith("mapping the 4 recorded frames of ")
        line = process.stdout.readline()
        assert line.startswith(f"web view of {room.recording.name} on http://127.0.0.1:"), line
        url = line.split(" on ", 1)[1].strip()
        assert get(url)[0] == 200
        assert get(url.split("?")[0])[0] == 401
        assert get(url.replace("?token=", "?key="))[0] == 200  # the login form sends its one field as key
        process.terminate()
        assert process.wait(STOP_SECONDS) == 0
        with pytest.raises(urllib.error.URLError):  # the server it started is gone too
            urllib.request.urlopen(url, timeout=5)
    finally:
        process.kill()
        process.wait()


@needs_browser
def test_ogclient_view_draws_a_snapshot_as_the_server_renders_it(room: Room) -> None:
    process = start("ogclient", "view", str(room.snapshot))
    try:
        line = process.stdout.readline()
        assert line.startswith("web view of room.safetensors on http://127.0.0.1:"), line
        url = line.split(" on ", 1)[1].strip()
        with browser() as chromium:
            page = chromium.new_page()
            page.goto(url + fragment(room.c2w, room.camera))
            page.wait_for_function("window.ogmapReady === true || window.ogmapError", timeout=PAGE_SECONDS * 1000)
            agreement = psnr(screenshot(page), room.expected)
            assert agreement >= MIN_PSNR, f"PSNR {agreement:.2f} dB"
    finally:
        process.terminate()
        process.wait(30)


def test_with_tls_the_web_port_speaks_only_https(tmp_path) -> None:
    ca = make_ca(tmp_path / "pki")
    configured = web_settings(tmp_path)
    ca.serve(configured.access)
    with serving(configured) as running:
        port = running.server.web.port
        trusting = ssl.create_default_context(cafile=str(ca.ca))
        with urllib.request.urlopen(f"https://127.0.0.1:{port}/static/style.css", context=trusting,
                                    timeout=30) as response:
            assert response.status == 200
        with pytest.raises((urllib.error.URLError, ConnectionError, http.client.HTTPException)):
            urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=30)


def test_with_mutual_tls_a_client_certificate_names_the_caller(tmp_path) -> None:
    ca = make_ca(tmp_path / "pki", clients=("alice", "bob"))
    configured = web_settings(tmp_path)
    ca.serve(configured.access, mutual=True)
    with serving(configured) as running:
        alice = ca.clients["alice"]
        channel, stub = connect(running.address, 10, Transport(ca=str(ca.ca), cert=str(alice.cert), key=str(alice.key)))
        with channel:
            mine = stub.CreateSession(create_request(FROZEN)).session_id
        index = f"https://127.0.0.1:{running.server.web.port}/"

        def context(name: str | None) -> ssl.SSLContext:
            trusting = ssl.create_default_context(cafile=str(ca.ca))
            if name:
                trusting.load_cert_chain(str(ca.clients[name].cert), str(ca.clients[name].key))
            return trusting

        for name, sees in (("alice", True), ("bob", False)):
            with urllib.request.urlopen(index, context=context(name), timeout=30) as response:
                assert (mine.encode() in response.read()) == sees
        with pytest.raises((urllib.error.URLError, ConnectionError, ssl.SSLError)):
            urllib.request.urlopen(index, context=context(None), timeout=30).read()


@pytest.mark.parametrize(("flags", "problem"), [
    ({"web_port": 70000}, r"live.web_port is out of range: must be in \[-1, 65535\]"),
    ({"web_seconds": 0.0}, "live.web_seconds is out of range: must be > 0 and finite"),
    ({"web_port": 0, "cluster": "auto"}, "live.web_port: the web view is not available in cluster mode"),
    ({"web_hosts": ["maps.example.org:8080"]}, "live.web_hosts"),
    ({"web_hosts": ["evil example"]}, "live.web_hosts"),
])
def test_web_settings_are_checked(flags, problem) -> None:
    with pytest.raises(ValueError, match=problem):
        load(flags=flags)
