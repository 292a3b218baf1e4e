"""What the web view shows of one map: its Gaussians as a .ply, the newest keyframe's input image and the
render from its pose, the keyframes' path and the map's statistics.

The Gaussians are decoded as seen from one point (colours and opacities depend on the viewpoint), like
``ogmap export``: the page's camera when it asks for one, else the mapped cameras' centroid. Decoding
holds the mapper's lock like a Render call, so it is done at most once per ``min_seconds`` for a map
and kept until the map has a new keyframe: however many pages watch, mapping pays for one decode.
The map answers through its ``MapLook``: a mapper in this process, or a session's in a worker process.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from ogserver.live.map_look import MapLook
from ogserver.live.views import Shown
from ogserver.web.horizon import world_up

CENTER_DECIMALS = 3  # a viewpoint to the millimetre: pages at one pose share one decode


class Source(Protocol):
    """One map as the web view sees it: a session's, or a snapshot's or recording's (``ogserver view``)."""

    id: str
    label: str
    look: MapLook

    def shown(self) -> Shown:
        """The keyframe whose input image the page shows beside the render from its pose (with that render
        where one was made already: the recording's views), and the map's version, which changes when the
        map has changed enough to be fetched again (each keyframe)."""
        ...

    def keyframe_path(self) -> np.ndarray:
        """The keyframes' camera-to-world poses (n, 4, 4), in mapping order: the path the page draws."""
        ...

    def counters(self) -> dict[str, Any]:
        """Frame counts and rates to show beside the map's statistics."""
        ...


class Busy:
    """What the web view's work took: its decodes and renders (they hold the mapper's lock, so mapping waits
    for them) and the CPU seconds of every request it answered, those included."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.count = 0
        self.seconds = 0.0  # the decodes' and renders' wall time, the mapper's lock held
        self.cpu_seconds = 0.0

    @contextmanager
    def holding(self, lock: AbstractContextManager[Any]) -> Iterator[None]:
        """Hold ``lock`` (the mapper's) for one decode or render and count it, with the CPU that the process's
        other threads (the compiled kernels' pool) spent meanwhile: mapping waits on the lock, so that is the
        work's too. The calling thread's own CPU is counted with its request (``request``). For a map in a
        worker process ``lock`` is none (the worker holds its mapper's), and the time is the call's."""
        with lock:
            wall, process, thread = time.perf_counter(), time.process_time(), time.thread_time()
            try:
                yield
            finally:
                others = (time.process_time() - process) - (time.thread_time() - thread)
                with self._lock:
                    self.count += 1
                    self.seconds += time.perf_counter() - wall
                    self.cpu_seconds += max(others, 0.0)

    @contextmanager
    def request(self) -> Iterator[None]:
        """Count the CPU seconds of the calling thread while it answers one request."""
        started = time.thread_time()
        try:
            yield
        finally:
            with self._lock:
                self.cpu_seconds += time.thread_time() - started


@dataclass
class Decoded:
    version: int
    center: tuple[float, ...]
    ply: bytes
    count: int
    at: float  # time.monotonic() when it was decoded


class MapView:
    """One source's decoded Gaussians and render, made at most once per ``min_seconds`` each."""

    def __init__(self, source: Source, min_seconds: float, busy: Busy | None = None) -> None:
        self.source = source
        self.min_seconds = min_seconds
        self.busy = busy or Busy()
        self._lock = threading.Lock()
        self._decoded: Decoded | None = None
        self._render: tuple[int, bytes] | None = None  # the version whose newest keyframe it renders, the JPEG

    def splats(self, center: np.ndarray | None) -> Decoded:
        """The map's Gaussians seen from ``center`` (None: the default viewpoint), decoded again only when
        the map has a new keyframe or another viewpoint is asked for, and not sooner than ``min_seconds``
        after the last decode (what is asked for meanwhile waits, or gets the last decode of that viewpoint)."""
        look = self.source.look
        with self._lock:
            if center is None:
                center = look.viewpoint()
            key = tuple(np.round(np.asarray(center, dtype=np.float64), CENTER_DECIMALS).tolist())
            version, last = self.source.shown().keyframes, self._decoded
            if last is not None and last.center == key:
                if last.version == version or time.monotonic() - last.at < self.min_seconds:
                    return last
            elif last is not None:
                time.sleep(max(0.0, last.at + self.min_seconds - time.monotonic()))
            with self.busy.holding(look.lock):
                splats = look.splats(np.asarray(key))
            self._decoded = Decoded(version, key, splats.ply, splats.count, time.monotonic())
            return self._decoded

    def render_jpeg(self) -> bytes | None:
        """The map rendered from the shown keyframe's pose: the recording's render of it, else one of its own."""
        shown, look = self.source.shown(), self.source.look
        if shown.frame is None:
            return None
        if shown.render is not None:
            return shown.render
        with self._lock:
            if self._render is None or self._render[0] != shown.keyframes:
                with self.busy.holding(look.lock):
                    jpeg = look.render_jpeg(shown.frame.pose, shown.frame.intrinsics)
                self._render = (shown.keyframes, jpeg)
            return self._render[1]

    def state(self) -> dict[str, Any]:
        """What the page polls: the map's version, statistics, the keyframes' path, the world's up (which
        the page keeps its horizon level to) and the newest keyframe."""
        look, shown = self.source.look, self.source.shown()
        stats, frame = look.stats(), shown.frame
        decoded = self._decoded
        poses = self.source.keyframe_path()
        latest = None
        if frame is not None:
            intrinsics = frame.intrinsics
            latest = {"sensor_ns": frame.sensor_ns, "keyframe": frame.keyframe,
                      "c2w": np.asarray(frame.pose).ravel().tolist(),
                      "fx": intrinsics.fx, "fy": intrinsics.fy, "cx": intrinsics.cx, "cy": intrinsics.cy,
                      "width": intrinsics.width, "height": intrinsics.height, "format": frame.color.format}
        start = latest["c2w"] if latest else path_pose(look, poses)
        return {
            "id": self.source.id, "label": self.source.label, "version": shown.keyframes, "start": start,
            "up": world_up(poses),
            "stats": {"frames": stats.frames, "keyframes": len(poses), "anchors": stats.anchors,
                      "gaussians_in_map": decoded.count if decoded else 0, "device": stats.device,
                      **self.source.counters()},
            "path": poses[:, :3, 3].round(4).tolist(), "latest": latest,
        }


def path_pose(look: MapLook, poses: np.ndarray) -> list[float]:
    """Where a page without a keyframe's input starts: the last keyframe's pose, else at the default viewpoint
    looking at the anchors' mean (world +y down in the image, as in OpenCV-style datasets)."""
    if len(poses):
        return poses[-1].ravel().tolist()
    eye, target = look.viewpoint(), look.anchor_centroid()
    forward = target - eye if np.linalg.norm(target - eye) > 1e-6 else np.array([0.0, 0.0, 1.0])
    forward = forward / np.linalg.norm(forward)
    right = np.cross([0.0, 1.0, 0.0], forward)
    right = right / np.linalg.norm(right) if np.linalg.norm(right) > 1e-6 else np.array([1.0, 0.0, 0.0])
    c2w = np.eye(4)
    c2w[:3, :3] = np.stack([right, np.cross(forward, right), forward], axis=1)
    c2w[:3, 3] = eye
    return c2w.ravel().tolist()
