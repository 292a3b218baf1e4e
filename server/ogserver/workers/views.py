"""A session in a worker process as the live views see it: the frames it mapped (``Latest``) and its map's
answers (``MapLook``), each read with one call to its worker.

The views in the server's process (the web view, the Foxglove view) use these as they use an in-process
session's ``LatestFrame`` and ``MapperLook``; the worker answers from the session's own, holding its
mapper's lock there. The server reads frames as a reader of its own (``SERVER_READER``), beside the
worker's ``LiveView``, which records the keyframes' views. A call whose worker has stopped, or whose
session has closed, raises the worker's refusal (UNAVAILABLE, NOT_FOUND): the views show the session as
gone.
"""

from __future__ import annotations

from contextlib import nullcontext
from typing import Any

import numpy as np

from ogmapping.frames.camera import Intrinsics
from ogmapping.persist.export import ColoredPoints
from ogmapping.stats import MapStats
from ogserver.live.map_look import Splats
from ogserver.live.views import Pending, Shown
from ogserver.workers.process import Worker

SERVER_READER = "server"  # the server's place among the readers of a session's LatestFrame in a worker
QUESTIONS = frozenset({"refines", "viewpoint", "anchor_centroid", "splats", "render_jpeg", "points", "stats",
                       "keyframe_path"})  # MapLook's, all a worker answers


class WorkerLatest:
    """A ``Latest``: the frames a session in ``worker`` mapped."""

    def __init__(self, worker: Worker, session_id: str) -> None:
        self._worker = worker
        self._session_id = session_id

    def take(self) -> Pending | None:
        return self._worker.call("take_latest", self._session_id)

    def shown(self) -> Shown:
        return self._worker.call("shown", self._session_id)


class WorkerLook:
    """A ``MapLook``: the map of a session in ``worker``."""

    lock = nullcontext()  # the worker holds the mapper's lock for each answer

    def __init__(self, worker: Worker, session_id: str) -> None:
        self._worker = worker
        self._session_id = session_id

    def _ask(self, question: str, *args: object) -> Any:
        return self._worker.call("look", self._session_id, question, *args)

    def refines(self) -> bool:
        return self._ask("refines")

    def viewpoint(self) -> np.ndarray:
        return self._ask("viewpoint")

    def anchor_centroid(self) -> np.ndarray:
        return self._ask("anchor_centroid")

    def splats(self, center: np.ndarray) -> Splats:
        return self._ask("splats", center)

    def render_jpeg(self, c2w: np.ndarray, intrinsics: Intrinsics) -> bytes:
        return self._ask("render_jpeg", c2w, intrinsics)

    def points(self, max_points: int) -> ColoredPoints:
        return self._ask("points", max_points)

    def stats(self) -> MapStats:
        return self._ask("stats")

    def keyframe_path(self) -> np.ndarray:
        return self._ask("keyframe_path")
