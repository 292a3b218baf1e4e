"""The live view's thread: each session's latest render, trajectory and map, to Foxglove and the recordings.

Every ``view_seconds`` it takes what each session mapped since the last look (``LatestFrame``) and
publishes, to the Foxglove clients subscribed (``--foxglove-port``): the camera poses and the camera's
path so far (refined ones too, in a session that refines poses), the input image, the map rendered from
the latest pose and the map as a point cloud; and, when a keyframe was
among those frames, writes the render and point cloud of the newest keyframe into the session's
recording (once more when the session closes, so its recording ends with the final map). Rendering
and decoding hold the mapper's lock like a Render call, between optimisation iterations; nothing is
rendered or decoded that no client watches and no recording wants, and the rate bounds the rest
(``bench/RESULTS.md`` measures what it costs the mapping).

With worker processes, each worker's own ``LiveView`` records its sessions' views, and the server's
(Foxglove only) reads the sessions through their workers (``workers/views.py``); a session whose worker
is gone is left out, and its topics withdrawn, from the next look on.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field

from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
from foxglove_schemas_protobuf.PointCloud_pb2 import PointCloud
from foxglove_schemas_protobuf.PosesInFrame_pb2 import PosesInFrame
from google.protobuf.message import Message
from ogapi import recording as layout

from ogmapping.persist.export import ColoredPoints
from ogserver.errors import ServiceError
from ogserver.live.channels import session_prefix
from ogserver.live.foxglove_ws import FoxgloveServer
from ogserver.live.views import (
    TOPIC_REFINED_TRAJECTORY,
    TOPIC_TRAJECTORY,
    FrameIds,
    MappedFrame,
    Pending,
    Trajectory,
    image,
    points_message,
)
from ogserver.recording.recorder import transform
from ogserver.sessions.hosting import ViewedHost, ViewedSession
from ogserver.sessions.session import Session
from ogserver.settings import Live

log = logging.getLogger(__name__)
LIVE_TOPICS: dict[str, type[Message]] = {
    layout.TOPIC_TRANSFORM: FrameTransform, layout.TOPIC_COLOR: CompressedImage,
    layout.TOPIC_RENDER: CompressedImage, layout.TOPIC_MAP: PointCloud, TOPIC_TRAJECTORY: PosesInFrame,
}
# Sessions that refine poses (``poses.refine``) have these too: the refined camera and its path.
REFINED_TOPICS: dict[str, type[Message]] = {
    layout.TOPIC_REFINED_TRANSFORM: FrameTransform, TOPIC_REFINED_TRAJECTORY: PosesInFrame,
}


@dataclass
class Looks:
    """One session's renders and point cloud, each made at most once per look."""

    session: ViewedSession
    max_points: int
    renders: dict[int, bytes] = field(default_factory=dict)  # by id() of the frame, alive for the look
    points: ColoredPoints | None = None

    def render(self, frame: MappedFrame) -> bytes:
        """The map rendered from the frame's pose and camera, to show beside the input image."""
        if id(frame) not in self.renders:
            self.renders[id(frame)] = self.session.look.render_jpeg(frame.pose, frame.intrinsics)
        return self.renders[id(frame)]

    def map(self) -> ColoredPoints:
        if self.points is None:
            self.points = self.session.look.points(self.max_points)
        return self.points


class LiveView:
    """``registry``: the sessions to look at; with ``settings.record_views`` the in-process ``Registry``,
    whose sessions' recordings it writes."""

    def __init__(self, registry: ViewedHost, settings: Live, foxglove: FoxgloveServer | None) -> None:
        self.registry = registry
        self.settings = settings
        self.foxglove = foxglove
        self._advertised: set[str] = set()
        self._paths: dict[str, tuple[Trajectory, Trajectory]] = {}  # by session: the client's and the refined
        self.busy_seconds = 0.0  # spent publishing and recording views (rendering and decoding, mostly)
        self.looks = 0  # sessions looked at with something new
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="live-view", daemon=True)
        if settings.record_views:
            registry.before_close(self.last_look)

    def start(self) -> LiveView:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread.ident is not None:
            self._thread.join()
            log.info("live view: %d session looks, %.1f s making and publishing views", self.looks, self.busy_seconds)
        if self.foxglove is not None:
            self.foxglove.stop()

    def _run(self) -> None:
        while not self._stop.wait(self.settings.view_seconds):
            self.look()

    def look(self) -> None:
        """Publish and record what every session mapped since the last look."""
        sessions = self.registry.sessions()
        self._advertise(sessions)
        for session in sessions:
            start = time.perf_counter()
            try:
                pending = session.latest.take()
                if pending is None:
                    continue
                looks = Looks(session, self.settings.view_points)
                if self.foxglove is not None:
                    self._publish(session.id, pending, looks, self.foxglove)
                if self.settings.record_views and pending.keyframe is not None:
                    self._record(session, pending.keyframe, looks)
            except ServiceError as gone:  # closed meanwhile, or its worker process stopped: the next look drops it
                log.debug("session %s: no view (%s)", session.id, gone.message)
                continue
            except Exception:  # one session's view must not stop the others'
                log.exception("session %s: the live view failed", session.id)
            self.busy_seconds += time.perf_counter() - start
            self.looks += 1

    def last_look(self, session: Session) -> None:
        """A closing session's recording ends with its final map: the newest keyframe not yet recorded."""
        pending = session.latest.take()
        if pending is None or pending.keyframe is None:
            return
        try:
            self._record(session, pending.keyframe, Looks(session, self.settings.view_points))
        except Exception:  # the session closes regardless
            log.exception("session %s: its last view could not be recorded", session.id)

    def _advertise(self, sessions: list[ViewedSession]) -> None:
        """Offer every open session's topics to Foxglove clients (those of poses refined where the session
        refines them), and withdraw those of closed ones."""
        if self.foxglove is None:
            return
        open_ids = {session.id for session in sessions}
        for session in sessions:
            if session.id in self._advertised:
                continue
            try:
                refines = session.look.refines()
            except ServiceError:  # gone before it was shown
                open_ids.discard(session.id)
                continue
            for topic, message_type in (LIVE_TOPICS | (REFINED_TOPICS if refines else {})).items():
                self.foxglove.advertise(session_prefix(session.id) + topic, message_type)
            self._paths[session.id] = (Trajectory(), Trajectory())
        for session_id in self._advertised - open_ids:
            self.foxglove.withdraw(session_prefix(session_id) + "/")
            self._paths.pop(session_id, None)
        self._advertised = open_ids

    def _publish(self, session_id: str, pending: Pending, looks: Looks, foxglove: FoxgloveServer) -> None:
        prefix, frames, latest = session_prefix(session_id), FrameIds.of_session(session_id), pending.latest
        if foxglove.wants(prefix + layout.TOPIC_TRANSFORM):
            for sensor_ns, c2w in pending.poses:
                foxglove.publish(prefix + layout.TOPIC_TRANSFORM, transform(sensor_ns, c2w, frames.world,
                                                                            frames.camera), sensor_ns)
        if foxglove.wants(prefix + layout.TOPIC_REFINED_TRANSFORM):
            for sensor_ns, c2w in pending.refined:
                foxglove.publish(prefix + layout.TOPIC_REFINED_TRANSFORM,
                                 transform(sensor_ns, c2w, frames.world, frames.refined_camera), sensor_ns)
        client_path, refined_path = self._paths.setdefault(session_id, (Trajectory(), Trajectory()))
        client_path.extend(pending.poses)
        refined_path.extend(pending.refined)
        for topic, path in ((TOPIC_TRAJECTORY, client_path), (TOPIC_REFINED_TRAJECTORY, refined_path)):
            if path.poses and foxglove.wants(prefix + topic):
                foxglove.publish(prefix + topic, path.message(frames), path.sensor_ns)
        if foxglove.wants(prefix + layout.TOPIC_COLOR):
            color = CompressedImage()
            color.CopyFrom(latest.color)
            color.frame_id = frames.camera
            foxglove.publish(prefix + layout.TOPIC_COLOR, color, latest.sensor_ns)
        if foxglove.wants(prefix + layout.TOPIC_RENDER):
            foxglove.publish(prefix + layout.TOPIC_RENDER, image(looks.render(latest), latest.sensor_ns, frames),
                             latest.sensor_ns)
        if foxglove.wants(prefix + layout.TOPIC_MAP):
            foxglove.publish(prefix + layout.TOPIC_MAP, points_message(looks.map(), latest.sensor_ns, frames),
                             latest.sensor_ns)

    def _record(self, session: Session, keyframe: MappedFrame, looks: Looks) -> None:
        frames = FrameIds()
        views: list[tuple[str, Message]] = [
            (layout.TOPIC_RENDER, image(looks.render(keyframe), keyframe.sensor_ns, frames)),
            (layout.TOPIC_MAP, points_message(looks.map(), keyframe.sensor_ns, frames)),
        ]
        session.latest.rendered = (keyframe, looks.render(keyframe))  # the web view shows it too
        try:
            session.recorder.write_views(views, keyframe.sensor_ns)
        except ServiceError:  # the recorder logged it, and the session refuses frames from now on
            return
