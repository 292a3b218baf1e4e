"""The web view's free camera in a real browser: the first view is level (the synthetic room's up is z, the
kitchen's its gravity), reset and frame-the-scene, the link to a view reproduces it, a bad fragment says
so, the panel hides, the help lists the keys, the path grows with the session, a snapshot shows its
keyframes, and the console stays free of errors and warnings. Screenshots are kept in the test's tmp_path."""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from ogapi.v1 import mapping_pb2 as pb
from ogclient.connection import SessionRef
from ogclient.evaluation import snapshot_bytes
from ogclient.streaming import stream_frames
from ogserver.web import still

from ogmapping.quality.evaluation import open_frames

from .browser import PAGE_SECONDS, browser, needs_browser
from .inprocess import Running, serving
from .scene import TINY, create_request, messages, scene
from .test_web_view import web_settings

LEVEL_DEGREES = 5.0
WAIT_MS = PAGE_SECONDS * 1000
KITCHEN_FRAMES, KITCHEN_STRIDE = "0:400", 40  # ten frames over the sequence: their right axes fix the up
KITCHEN_SCALE = 0.25

pytestmark = needs_browser


@dataclass
class Served:
    url: str  # the map's page, credential included
    running: Running
    session: SessionRef


class Page:
    """A page of the web view, its console's errors and warnings (and uncaught exceptions) collected. Pages
    are closed by the ``pages`` fixture: each one open keeps polling, and the server bounds connections."""

    def __init__(self, chromium, url: str, ready: bool = True) -> None:
        self.page = chromium.new_page(viewport={"width": 800, "height": 500})
        OPEN.append(self.page)
        self.problems: list[str] = []
        self.page.on("console", lambda message: self.problems.append(f"{message.type}: {message.text}")
                     if message.type in ("error", "warning") else None)
        self.page.on("pageerror", lambda error: self.problems.append(f"exception: {error}"))
        self.page.goto(url)
        if ready:
            self.ready()

    def ready(self) -> None:
        self.page.wait_for_function("window.ogmapReady === true || window.ogmapError", timeout=WAIT_MS)
        assert self.page.evaluate("window.ogmapError") is None

    def camera(self) -> dict:
        return self.page.evaluate("window.ogmapCamera()")

    def c2w(self) -> np.ndarray:
        return np.array(self.camera()["c2w"]).reshape(4, 4)

    def keep(self, path: Path) -> None:
        """A screenshot, kept as the test's artefact."""
        self.page.screenshot(path=str(path))

    def drag(self, dx: float, dy: float, button: str = "left") -> None:
        mouse = self.page.mouse
        mouse.move(300, 250)
        mouse.down(button=button)
        mouse.move(300 + dx, 250 + dy, steps=5)
        mouse.up(button=button)

    def hold(self, key: str, seconds: float) -> None:
        self.page.keyboard.down(key)
        self.page.wait_for_timeout(seconds * 1000)
        self.page.keyboard.up(key)

    def settled(self) -> None:
        """The camera's last move drawn (one animation frame)."""
        self.page.evaluate("new Promise((done) => requestAnimationFrame(() => requestAnimationFrame(done)))")


def roll_degrees(c2w: np.ndarray, up) -> float:
    """How far the camera's horizon tilts from the world's: its x axis against the plane normal to ``up``."""
    right, up = c2w[:3, 0], np.asarray(up, np.float64) / np.linalg.norm(up)
    return math.degrees(math.asin(min(1.0, abs(float(right @ up)))))


OPEN: list = []


@pytest.fixture(scope="module")
def browser_once() -> Iterator:
    with browser() as launched:
        yield launched


@pytest.fixture
def chromium(browser_once) -> Iterator:
    """The module's browser, the test's pages closed after it."""
    yield browser_once
    while OPEN:
        OPEN.pop().close()


@pytest.fixture(scope="module")
def room(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    with serving(web_settings(tmp_path_factory.mktemp("room"))) as running:
        session = SessionRef.from_credentials(running.stub.CreateSession(create_request(TINY)))
        stream_frames(running.stub, session, messages(scene()), None, False)
        yield Served(f"http://127.0.0.1:{running.server.web.port}/map/{session.session_id}?token={session.token}",
                     running, session)


def test_the_first_view_is_level_and_reset_and_frame_keep_it_so(room: Served, chromium, tmp_path: Path) -> None:
    page = Page(chromium, room.url)
    first = page.c2w()
    page.keep(tmp_path / "room-first-view.png")
    assert roll_degrees(first, [0, 0, 1]) < LEVEL_DEGREES
    assert page.page.locator("#loading").is_hidden()
    page.drag(120, 40)
    page.hold("KeyW", 0.3)
    page.settled()
    moved = page.c2w()
    assert not np.allclose(moved, first, atol=1e-3)
    assert roll_degrees(moved, [0, 0, 1]) < LEVEL_DEGREES  # the horizon stays level while the camera turns
    page.page.keyboard.press("r")
    page.settled()
    assert np.allclose(page.c2w(), first, atol=1e-9)
    page.page.keyboard.press("f")
    page.settled()
    framed = page.c2w()
    assert not np.allclose(framed, first, atol=1e-3) and roll_degrees(framed, [0, 0, 1]) < LEVEL_DEGREES
    page.keep(tmp_path / "room-framed.png")
    assert page.problems == []


def test_a_link_to_the_view_opens_that_view(room: Served, chromium, tmp_path: Path) -> None:
    page = Page(chromium, room.url)
    page.page.keyboard.press("m")  # fly
    page.drag(-80, 30)
    page.hold("KeyD", 0.2)
    page.drag(40, -20, button="right")
    page.page.mouse.wheel(0, 200)
    page.settled()
    here = page.camera()
    assert here["mode"] == "fly"
    page.page.click("#copy-link")
    link = page.page.locator("#link").input_value()
    assert link.startswith(room.url + "#eye=")
    opened = Page(chromium, link)
    there = opened.camera()
    assert np.allclose(there["c2w"], here["c2w"], atol=1e-9), (there["c2w"], here["c2w"])
    assert (there["mode"], there["fov"], there["up"]) == (here["mode"], here["fov"], here["up"])
    opened.keep(tmp_path / "room-linked-view.png")
    assert page.problems == [] and opened.problems == []


@pytest.mark.parametrize("fragment", ["#pose=1,2,3", "#eye=1,2&look=0,0,1", "#nothing"])
def test_a_bad_fragment_says_so_and_shows_the_first_view(room: Served, chromium, fragment: str) -> None:
    page = Page(chromium, room.url + fragment)
    message = page.page.locator("#message")
    assert message.is_visible()
    assert "not a view this page can open" in message.inner_text()
    assert roll_degrees(page.c2w(), [0, 0, 1]) < LEVEL_DEGREES
    page.page.click("#message-close")
    assert message.is_hidden()
    assert page.problems == []


def test_the_panel_hides_and_the_help_lists_the_keys(room: Served, chromium, tmp_path: Path) -> None:
    page = Page(chromium, room.url)
    panel, help_sheet = page.page.locator("#panel"), page.page.locator("#help")
    assert panel.is_visible() and help_sheet.is_hidden()
    page.page.keyboard.press("p")
    assert panel.is_hidden()
    page.keep(tmp_path / "room-panel-hidden.png")
    page.page.click("#panel-toggle")
    assert panel.is_visible()
    page.page.keyboard.press("?")
    assert help_sheet.is_visible()
    text = help_sheet.inner_text()
    assert all(key in text for key in ("W A S D", "Q E", "M", "R", "F", "L", "P", "?"))
    page.keep(tmp_path / "room-help.png")
    page.page.keyboard.press("Escape")
    assert help_sheet.is_hidden()
    page.page.select_option("#mode", "fly")
    assert page.camera()["mode"] == "fly"
    assert page.problems == []


def test_the_page_waits_for_the_first_keyframe_and_its_path_grows_while_the_session_maps(tmp_path: Path,
                                                                                        chromium) -> None:
    frames = messages(scene("0:30"))
    with serving(web_settings(tmp_path)) as running:
        session = SessionRef.from_credentials(running.stub.CreateSession(create_request(TINY)))
        page = Page(chromium, f"http://127.0.0.1:{running.server.web.port}/map/{session.session_id}"
                              f"?token={session.token}", ready=False)
        loading = page.page.locator("#loading")
        page.page.wait_for_function("document.getElementById('loading-text').textContent.includes('waiting')",
                                    timeout=WAIT_MS)
        assert loading.is_visible() and "waiting for the first keyframe" in loading.inner_text()
        assert page.page.evaluate("window.ogmapReady") is None
        page.keep(tmp_path / "live-waiting.png")
        stream_frames(running.stub, session, frames[:2], None, False)
        page.ready()
        assert loading.is_hidden()
        before = page.camera()["pathPoints"]
        stream_frames(running.stub, session, frames[2:], None, False)
        keyframes = stats(running, session).keyframes
        assert keyframes > 8 > before  # past the path's first buffer
        page.page.wait_for_function(f"window.ogmapCamera().pathPoints === {keyframes}", timeout=WAIT_MS)
        page.keep(tmp_path / "live-path.png")
        assert page.problems == []


def stats(running, session: SessionRef) -> pb.Stats:
    return running.stub.GetStats(pb.GetStatsRequest(session_id=session.session_id), metadata=session.metadata())


def test_a_snapshots_page_shows_its_keyframes_and_path(room: Served, chromium, tmp_path: Path) -> None:
    snapshot = tmp_path / "room.safetensors"
    snapshot.write_bytes(snapshot_bytes(room.running.stub, room.session))
    server, url = still.serve(still.open_map(snapshot, "cpu", lambda _: None))
    try:
        page = Page(chromium, url)
        keyframes = stats(room.running, room.session).keyframes
        assert page.camera()["pathPoints"] == keyframes > 1
        shown = dict(zip(page.page.locator("#stats dt").all_inner_texts(),
                         page.page.locator("#stats dd").all_inner_texts(), strict=True))
        assert shown["keyframes"] == str(keyframes)
        assert roll_degrees(page.c2w(), [0, 0, 1]) < LEVEL_DEGREES
        page.keep(tmp_path / "snapshot-first-view.png")
        assert page.problems == []
    finally:
        server.stop()


def test_the_kitchens_first_view_is_level(seven_scenes: Path, chromium, tmp_path: Path) -> None:
    frames = open_frames(str(seven_scenes), "7scenes", KITCHEN_FRAMES, KITCHEN_STRIDE, KITCHEN_SCALE)
    gravity = np.loadtxt(seven_scenes / "data" / "gravity-direction.txt")  # the data's own, pointing down
    with serving(web_settings(tmp_path)) as running:
        session = SessionRef.from_credentials(running.stub.CreateSession(create_request(TINY)))
        stream_frames(running.stub, session, messages(frames), None, False)
        page = Page(chromium, f"http://127.0.0.1:{running.server.web.port}/map/{session.session_id}"
                              f"?token={session.token}")
        page.keep(tmp_path / "kitchen-first-view.png")
        assert roll_degrees(page.c2w(), -gravity) < LEVEL_DEGREES
        page.page.keyboard.press("f")
        page.settled()
        assert roll_degrees(page.c2w(), -gravity) < LEVEL_DEGREES
        page.keep(tmp_path / "kitchen-framed.png")
        assert page.problems == []
