"""One mapping session: its map, a bounded frame queue and the worker thread that maps it.

Frames are mapped strictly in arrival order by the session's own thread, so sessions map in
parallel while renders, stats and snapshots (other threads) are served by the mapper between
optimisation iterations.
"""

from __future__ import annotations

import hmac
import json
import logging
import queue
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import grpc
from ogapi.images import encode_color, encode_depth
from ogapi.v1 import mapping_pb2 as pb

from ogmapping.frame import Frame
from ogmapping.mapper import Mapper
from ogserver.errors import ServiceError, exhausted
from ogserver.recorder import Recorder
from ogserver.settings import Limits
from ogserver.validation import RenderSpec

log = logging.getLogger(__name__)
RENDER_DEPTH_SCALE = 1000.0  # PNG16 renders are millimetres


def error_ack(index: int, error: ServiceError) -> pb.FrameAck:
    return pb.FrameAck(
        index=index, accepted=False,
        error=pb.Error(code=error.code.value[0], code_name=error.code.name, message=error.message),
    )


@dataclass
class Job:
    frame: Frame
    sequence: int
    received: float  # time.monotonic() when the frame was read
    sink: queue.SimpleQueue | None  # where the stream that sent it waits for its ack


class Session:
    def __init__(
        self, session_id: str, token: str, mapper: Mapper, config: pb.SessionConfig,
        recorder: Recorder, limits: Limits,
    ) -> None:
        self.id = session_id
        self.mapper = mapper
        self.config = config
        self.recorder = recorder
        self.limits = limits
        self.token = token
        self._started = time.monotonic()
        self._slots = threading.Semaphore(limits.queue_depth)
        self._jobs: queue.SimpleQueue[Job | None] = queue.SimpleQueue()
        self._lock = threading.Lock()
        self._closed = threading.Event()
        self._stream_sink: queue.SimpleQueue | None = None
        self.received = self.rejected = self.mapped = self.pending = 0
        self.anchors = 0
        self._first_received: float | None = None
        self._last_mapped: float | None = None
        self._worker = threading.Thread(target=self._run, name=f"session-{session_id[:8]}", daemon=True)
        self._worker.start()

    # ------------------------------------------------------------------ access

    def authenticate(self, token: str) -> None:
        if not token:
            raise ServiceError(grpc.StatusCode.UNAUTHENTICATED, "x-session-token: metadata is missing")
        if not hmac.compare_digest(token.encode(), self.token.encode()):
            raise ServiceError(grpc.StatusCode.UNAUTHENTICATED, "x-session-token: does not match the session")

    @property
    def streaming(self) -> bool:
        return self._stream_sink is not None

    @contextmanager
    def stream(self, sink: queue.SimpleQueue) -> Iterator[None]:
        """Claim the session's single frame stream; a second one would interleave frames."""
        with self._lock:
            if self._closed.is_set():
                raise ServiceError(grpc.StatusCode.NOT_FOUND, f"session_id: session {self.id} is closed")
            if self._stream_sink is not None:
                raise ServiceError(
                    grpc.StatusCode.FAILED_PRECONDITION, "session_id: the session already has an active frame stream"
                )
            self._stream_sink = sink
        try:
            yield
        finally:
            with self._lock:
                self._stream_sink = None

    # ------------------------------------------------------------------ frames

    def check_capacity(self) -> None:
        if self.limits.max_anchors and self.anchors >= self.limits.max_anchors:
            raise exhausted("frame", f"the map reached the server's limit of {self.limits.max_anchors} anchors")

    def count_rejected(self) -> None:
        with self._lock:
            self.rejected += 1

    def submit(self, frame: Frame, message: pb.Frame, sink: queue.SimpleQueue | None) -> bool:
        """Record and queue a validated frame, waiting while the queue is full; False once closed."""
        received, received_ns = time.monotonic(), time.time_ns()
        while not self._slots.acquire(timeout=0.2):
            if self._closed.is_set():
                return False
        with self._lock:
            if self._closed.is_set():
                self._slots.release()
                return False
            self.received += 1
            self.pending += 1
            sequence = self.received
            if self._first_received is None:
                self._first_received = received
        self.recorder.write_frame(message, frame, received_ns)
        self._jobs.put(Job(frame, sequence, received, sink))
        return True

    def _run(self) -> None:
        while (job := self._jobs.get()) is not None:
            try:
                ack = self._map(job)
            finally:
                with self._lock:
                    self.pending -= 1
                self._slots.release()
            self.recorder.write_ack(ack)
            if job.sink is not None:
                job.sink.put(("job", ack))

    def _map(self, job: Job) -> pb.FrameAck:
        try:
            result = self.mapper.process(job.frame)
        except Exception as error:  # the session survives a failing frame; the client sees why
            log.exception("session %s: mapping frame %d failed", self.id, job.frame.index)
            return error_ack(job.frame.index, ServiceError(grpc.StatusCode.INTERNAL, f"mapping failed: {error}"))
        with self._lock:
            self.mapped += 1
            self.anchors = result.anchors
            self._last_mapped = time.monotonic()
            waiting = self.pending - 1
        return pb.FrameAck(
            index=job.frame.index, accepted=True, sequence=job.sequence, keyframe=result.keyframe,
            anchors=result.anchors, gaussians=result.gaussians, iterations=result.iterations,
            latency_seconds=time.monotonic() - job.received, process_seconds=result.seconds,
            queue_depth=max(waiting, 0),
        )

    # ------------------------------------------------------------------ queries

    def render(self, spec: RenderSpec) -> pb.RenderResponse:
        start = time.perf_counter()
        rendered = self.mapper.render(spec.c2w, spec.intrinsics)
        response = pb.RenderResponse(width=spec.intrinsics.width, height=spec.intrinsics.height)
        if spec.color:
            response.color.encoding = spec.color_encoding
            response.color.data = encode_color(rendered.color, spec.color_encoding, spec.jpeg_quality)
        if spec.depth:
            response.depth.encoding = spec.depth_encoding
            response.depth.data = encode_depth(rendered.depth, spec.depth_encoding, RENDER_DEPTH_SCALE)
            if spec.depth_encoding == pb.DEPTH_PNG16:
                response.depth.depth_scale = RENDER_DEPTH_SCALE
        response.render_seconds = time.perf_counter() - start
        return response

    def stats(self) -> pb.Stats:
        engine = self.mapper.stats()
        with self._lock:
            elapsed = (
                self._last_mapped - self._first_received
                if self._last_mapped is not None and self._first_received is not None else 0.0
            )
            stats = pb.Stats(
                session_id=self.id, preset=self.config.preset, device=engine.device,
                frames=self.mapped, frames_received=self.received, frames_rejected=self.rejected,
                queue_depth=self.pending, processing_fps=self.mapped / elapsed if elapsed > 0 else 0.0,
                uptime_seconds=time.monotonic() - self._started,
            )
        stats.keyframes = engine.keyframes
        stats.anchors = engine.anchors
        stats.anchors_per_level.extend(engine.anchors_per_level)
        stats.gaussians = engine.gaussians
        stats.iterations = engine.iterations
        stats.timings.update(engine.timings)
        stats.engine_json = json.dumps(engine.to_dict())
        stats.config_json = self.config.config_json
        return stats

    def info(self) -> pb.SessionInfo:
        return pb.SessionInfo(
            session_id=self.id, preset=self.config.preset, label=self.config.label, device=self.config.device,
            created_unix=self.config.created_unix, frames=self.mapped, anchors=self.anchors,
            queue_depth=self.pending, streaming=self.streaming, recording=str(self.recorder.path),
        )

    def snapshot(self) -> bytes:
        return self.mapper.snapshot()

    # ------------------------------------------------------------------ end

    def close(self) -> None:
        """Stop taking frames, drop the queued ones, wait for the frame being mapped, end any stream."""
        with self._lock:
            if self._closed.is_set():
                return
            self._closed.set()
            sink = self._stream_sink
        dropped = 0
        while True:
            try:
                job = self._jobs.get_nowait()
            except queue.Empty:
                break
            if job is not None:
                dropped += 1
        with self._lock:
            self.pending -= dropped
        self._jobs.put(None)
        self._worker.join()
        if sink is not None:
            sink.put(("closed", None))
        if dropped:
            log.info("session %s: closed with %d queued frames dropped", self.id, dropped)
