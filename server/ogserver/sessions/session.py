"""One mapping session: its map, a bounded frame queue and the worker thread that maps it.

Frames are mapped strictly in arrival order by the session's own thread, so sessions map in parallel while renders,
stats and snapshots (other threads) are served by the mapper between optimisation iterations. A second thread
prepares the next queued frame (depth registration, ``Mapper.prepare``) while the worker maps the one before it, so
that work is off the mapping path. The worker records each frame as it takes it up, before mapping it, so the
recording holds exactly the frames the session mapped (or tried to): frames still queued when the session closes are
dropped unrecorded, and a replay maps what the original did. Every ``checkpoints.interval`` recorded frames the
worker, once the ack of the first frame it maps at or past that point is sent, writes a checkpoint of the map
(``recording/checkpoint.py``). A session resumed after a crash starts from its last checkpoint with a backlog: the
recorded frames after it that the session mapped (a realtime session's skipped ones stay skipped), which the worker
maps (they are already recorded) before any new frame. The session answers in engine results and its own counters;
the messages module turns them into ogapi messages.

A realtime session never makes the stream wait: beyond ``realtime_queue_depth`` waiting frames, the oldest waiting
one is skipped at once (acknowledged as skipped, never mapped, and recorded while the session's ``SkippedBudget``
covers it). Taking a frame out of the queue and recording it happen under one lock, on either path, so the recording
keeps arrival order and a replay maps every recorded frame, skipped ones included, in that order. Sequences number
the recorded frames: a skipped frame left out of the recording gives its number to the frames queued after it.

Pose corrections (CorrectPoses) reach the map between two frames: the worker holds ``_mapping`` while it maps a
frame, acknowledges it and writes any checkpoint due, and a correction takes it too, so the batch lands after the
last frame mapped, a checkpoint holds all of it or none, and the recording says after which frame (a replay and a
resume apply it there again). The frames mapped (``ledger.FrameLedger``) resolve what a correction or render names.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager, suppress
from pathlib import Path

import grpc
from ogapi import SESSION_METADATA_KEY
from ogapi.v1 import mapping_pb2 as pb

from ogmapping.frames.frame import Frame
from ogmapping.mapper import Mapper, PreparedFrame
from ogmapping.persist.state import MapState
from ogmapping.queries import Rendered
from ogmapping.runtime.time_budget import Budget
from ogmapping.stats import MapStats
from ogserver.access.tokens import TokenHash
from ogserver.api import messages, validation
from ogserver.errors import ServiceError
from ogserver.live.map_look import MapperLook
from ogserver.live.views import LatestFrame, MappedFrame
from ogserver.recording.checkpoint import Checkpoints, Position
from ogserver.recording.disk import StorageError
from ogserver.recording.recorder import FrameRecord, Recorder, frame_record
from ogserver.recording.skipped_budget import SkippedBudget
from ogserver.sessions import pose_corrections
from ogserver.sessions.backlog import Recorded, RecordedCorrections
from ogserver.sessions.counters import SessionCounters, rate
from ogserver.sessions.jobs import Job, prepare_next
from ogserver.sessions.ledger import TENSOR, FrameLedger
from ogserver.sessions.queued_bytes import ByteBudget, frame_bytes
from ogserver.sessions.stream_events import Acked, SessionClosed, StreamEvent
from ogserver.settings import Limits
from ogserver.throttled_log import ThrottledLog

log = logging.getLogger(__name__)
CLAMPED_LOG_SECONDS = 10.0


class Session:
    def __init__(
        self, config: pb.SessionConfig, token: TokenHash, mapper: Mapper, recorder: Recorder, limits: Limits,
        frame_seconds: float = 0.0, checkpoints: Checkpoints | None = None, start: Position | None = None,
        backlog: list[Recorded | RecordedCorrections] | None = None, recorded: Position | None = None,
        ledger: FrameLedger | None = None,
    ) -> None:
        """``start``: where the map stands; ``recorded``: the last frame the recording holds (``start``
        unless the backlog or skipped frames follow it)."""
        self.id = config.session_id
        self.mapper = mapper
        self.config = config
        self.recorder = recorder
        self.limits = limits
        self.token = token
        self.checkpoints = checkpoints
        self._backlog = list(backlog or ())
        self._ledger = ledger or FrameLedger()
        self._corrections = pose_corrections.Corrections(self.id, mapper, self._ledger, limits, recorder)
        self._mapping = threading.Lock()  # held while a frame is mapped or the map corrected (never inside _lock)
        start = start or Position()
        recorded = recorded or start
        # Sequences go on from the recording's last frame; this server run counts the backlog as received.
        self._sequence = recorded.sequence  # the last one given to a frame
        self._last_index = recorded.index
        self._mapped_position = start
        self._started = time.monotonic()
        self.realtime = config.realtime
        self._slots = threading.Semaphore(limits.queue_depth)
        self._queued_bytes = ByteBudget(limits.max_queued_bytes)
        self._skipped_budget = SkippedBudget(limits.max_skipped_recording_bytes,
                                             limits.skipped_recording_bytes_per_second)
        self._unrecorded = 0  # skipped frames left out of the recording
        # Jobs in arrival order (None: stop). Lock order: _intake, then _lock.
        self._intake = threading.Condition()
        self._jobs: deque[Job | None] = deque()
        self._lock = threading.Lock()
        self.latest = LatestFrame()  # what the live view and the recording's map views show next
        self.look = MapperLook(mapper)  # the map's answers to the live views
        self._clamped_log = ThrottledLog(log, CLAMPED_LOG_SECONDS)  # poses.refine: corrections held at the bound
        self._closed = threading.Event()
        # Each frame's optimisation stops after frame_seconds (0: no limit), or at once when the session closes.
        self._time_budget = Budget(seconds=frame_seconds or math.inf)
        self._stream_sink: queue.SimpleQueue[StreamEvent] | None = None
        self._rejected = self._mapped = self._skipped = 0
        self._received = self._pending = sum(isinstance(item, Recorded) for item in self._backlog)
        engine = mapper.stats()
        self._anchors, self._gaussians = engine.anchors, engine.gaussians  # a restored map starts with them
        self._first_received: float | None = self._started if self._backlog else None
        self._last_mapped: float | None = None
        # Prepares the next queued frame (``Mapper.prepare``) while the worker maps the one before it.
        self._preparer = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"prepare-{self.id[:8]}")
        self._worker = threading.Thread(target=self._run, name=f"session-{self.id[:8]}", daemon=True)
        self._worker.start()

    # ------------------------------------------------------------------ access

    @property
    def recording(self) -> Path:
        return self.recorder.path

    @property
    def streaming(self) -> bool:
        return self._stream_sink is not None

    @contextmanager
    def stream(self, sink: queue.SimpleQueue[StreamEvent]) -> Iterator[None]:
        """Claim the session's single frame stream; a second one would interleave frames."""
        with self._lock:
            if self._closed.is_set():
                raise ServiceError(grpc.StatusCode.NOT_FOUND, f"{SESSION_METADATA_KEY}: session {self.id} is closed")
            if self._stream_sink is not None:
                raise ServiceError(grpc.StatusCode.FAILED_PRECONDITION,
                                   f"{SESSION_METADATA_KEY}: the session already has an active frame stream")
            self._stream_sink = sink
        try:
            yield
        finally:
            with self._lock:
                self._stream_sink = None

    # ------------------------------------------------------------------ frames

    def check_capacity(self) -> None:
        """Refuse frames the session cannot take: its recording failed, or its map is full."""
        if self.recorder.failure is not None:
            raise self.recorder.failure
        if self.limits.max_anchors and self._anchors >= self.limits.max_anchors:
            raise ServiceError(grpc.StatusCode.RESOURCE_EXHAUSTED,
                               f"the map reached the server's limit of {self.limits.max_anchors} anchors")

    def offer(self, message: pb.Frame, max_pixels: int, sink: queue.SimpleQueue[StreamEvent] | None) -> bool:
        """Check, validate and queue a client's frame: ``submit``'s answer, or the ServiceError refusing it."""
        self.check_capacity()
        frame = validation.frame(message, max_pixels, self.mapper.config.octree)
        return self.submit(frame, message, sink)

    def count_rejected(self) -> None:
        with self._lock:
            self._rejected += 1

    def submit(self, frame: Frame, message: pb.Frame, sink: queue.SimpleQueue[StreamEvent] | None) -> bool:
        """Queue a validated frame, waiting while the queue is full (a realtime session skips the oldest
        waiting frame instead); False once closed, StorageError if the frame cannot be recorded."""
        received, received_ns = time.monotonic(), time.time_ns()
        try:
            record = frame_record(message, frame, received_ns)
        except Exception:
            log.exception("session %s: frame %d cannot be recorded", self.id, frame.index)
            raise StorageError(grpc.StatusCode.INTERNAL, "the server could not encode the frame for its recording") \
                from None
        if self.realtime:
            return self._submit_newest(frame, record, received, sink)
        while not self._slots.acquire(timeout=0.2):
            if self._closed.is_set():
                return False
        size = frame_bytes(frame)
        if not self._queued_bytes.acquire(size, self._closed):
            self._slots.release()
            return False
        with self._intake:
            job = self._enqueue(frame, record, received, sink, size)
            if job is None:
                self._queued_bytes.release(size)
                self._slots.release()
                return False
        return True

    def _enqueue(
        self, frame: Frame, record: FrameRecord, received: float, sink: queue.SimpleQueue[StreamEvent] | None,
        size: int,
    ) -> Job | None:
        """Count the frame in and queue it, the caller holding ``_intake``; None once closed."""
        with self._lock:
            if self._closed.is_set():
                return None
            self._received += 1
            self._pending += 1
            self._sequence += 1
            self._last_index = frame.index
            if self._first_received is None:
                self._first_received = received
            job = Job(frame, record, self._sequence, received, sink, size)
        self._jobs.append(job)
        self._intake.notify()
        return job

    def _submit_newest(
        self, frame: Frame, record: FrameRecord, received: float, sink: queue.SimpleQueue[StreamEvent] | None
    ) -> bool:
        """Queue the frame at once; the oldest waiting frames beyond ``realtime_queue_depth`` are skipped."""
        with self._intake:
            if self._enqueue(frame, record, received, sink, 0) is None:
                return False
            skipped = []
            while len(self._jobs) > self.limits.realtime_queue_depth:
                job = self._jobs.popleft()
                assert job is not None  # the stop marker is queued only once closed, and then nothing is
                skipped.append((job, self._skip(job)))
        for job, ack in skipped:
            if job.sink is not None:
                job.sink.put(Acked(ack))
        return True

    def _map_backlog(self) -> None:
        """A resumed session's recorded frames after its checkpoint, mapped again (not recorded again)."""
        while self._backlog and not self._closed.is_set():
            item = self._backlog.pop(0)
            with self._mapping:
                if isinstance(item, RecordedCorrections):
                    self._corrections.again(item)
                    continue
                try:
                    frame = validation.frame(item.message, self.limits.max_image_pixels, self.mapper.config.octree)
                    self._map(frame, item.sequence, time.monotonic())
                except ServiceError as refusal:  # a server restarted with lower limits than the frame was taken under
                    log.error("session %s: recorded frame %d (sequence %d) is refused on resume: %s", self.id,
                              item.message.index, item.sequence, refusal.message)
                with self._lock:
                    self._pending -= 1
                    self._mapped_position = Position(item.sequence, item.message.index)
                self._checkpoint_if_due()
        self._backlog = [item for item in self._backlog if isinstance(item, Recorded)]
        if self._backlog:
            log.warning("session %s: closed before its %d remaining recorded frames were mapped again", self.id,
                        len(self._backlog))
            with self._lock:
                self._pending -= len(self._backlog)
            self._backlog.clear()

    def _checkpoint_if_due(self) -> None:
        """After a frame is recorded, mapped and acknowledged: a checkpoint when one is due
        (``Checkpoints.write_if_due``). Its position is the last mapped frame's, so a resume maps the recorded
        frames after it that this session mapped (a realtime session's frames skipped since then stay skipped)."""
        with self._lock:
            position = self._mapped_position
        if self.checkpoints is None or self.recorder.failure or self._closed.is_set():
            return
        self.checkpoints.write_if_due(position, self._checkpoint_state)

    def _checkpoint_state(self) -> MapState:
        state = self.mapper.state(training_state=True)
        state.tensors[TENSOR] = self._ledger.tensor()
        return state

    def _skip(self, job: Job) -> pb.FrameAck:
        """Record a frame passed over for a newer one, and its skipped ack (or why it could not be recorded);
        beyond the session's ``SkippedBudget``, only the ack. The caller holds ``_intake``."""
        if not self._skipped_budget.take(job.record.size):
            return self._skip_unrecorded(job)
        refusal = self._record(job)
        with self._lock:
            self._pending -= 1
            if refusal is None:
                self._skipped += 1
            waiting = len(self._jobs)
            anchors, gaussians = self._anchors, self._gaussians
        if refusal is not None:
            return refusal
        ack = messages.skipped_ack(job.frame.index, job.sequence, anchors, gaussians,
                                   time.monotonic() - job.received, waiting)
        with suppress(StorageError):  # logged by the recorder, as for a mapped frame's ack
            self.recorder.write_ack(ack)
        return ack

    def _skip_unrecorded(self, job: Job) -> pb.FrameAck:
        """A skipped frame the recording does not take: the frames queued after it move up one sequence."""
        with self._lock:
            self._pending -= 1
            self._skipped += 1
            self._unrecorded += 1
            self._sequence -= 1
            for later in self._jobs:
                if later is not None:
                    later.sequence -= 1
            waiting = len(self._jobs)
            anchors, gaussians = self._anchors, self._gaussians
            first = self._unrecorded == 1
        if first:
            log.warning("session %s: skipped frames beyond its recording budget (%d bytes in all, %d per second) "
                        "are acknowledged as unrecorded and left out of the recording", self.id,
                        self.limits.max_skipped_recording_bytes, self.limits.skipped_recording_bytes_per_second)
        ack = messages.skipped_ack(job.frame.index, 0, anchors, gaussians, time.monotonic() - job.received, waiting)
        ack.unrecorded = True
        return ack

    def _record(self, job: Job) -> pb.FrameAck | None:
        """None once the recording holds the frame, else the error ack of a frame it cannot hold."""
        try:
            self.recorder.write_frame(job.record)
        except ServiceError as refusal:
            return messages.error_ack(job.frame.index, refusal)
        return None

    def _take(self) -> tuple[Job, pb.FrameAck | None] | None:
        """The next frame, recorded before a newer one can be skipped past it; None to stop."""
        with self._intake:
            while not self._jobs:
                self._intake.wait()
            job = self._jobs.popleft()
            if job is None:
                return None
            prepare_next(self._jobs, self._preparer, self.mapper)
            return job, self._record(job)

    def _run(self) -> None:
        self._map_backlog()
        while (taken := self._take()) is not None:
            job, refusal = taken
            with self._mapping:
                try:
                    ack = refusal or self._map_recorded(job)
                finally:
                    with self._lock:
                        self._pending -= 1
                    if not self.realtime:
                        self._queued_bytes.release(job.size)
                        self._slots.release()
                if job.sink is not None:
                    job.sink.put(Acked(ack))
                self._checkpoint_if_due()

    def _map_recorded(self, job: Job) -> pb.FrameAck:
        """A frame is mapped only once the recording holds it."""
        ack = self._map(job.frame, job.sequence, job.received, job.record, job.prepared)
        with self._lock:
            self._mapped_position = Position(job.sequence, job.frame.index)
        with suppress(StorageError):  # logged by the recorder; the frame is mapped and recorded, its ack is not
            self.recorder.write_ack(ack, job.record.sensor_ns)
        return ack

    def _map(self, frame: Frame, sequence: int, received: float, record: FrameRecord | None = None,
             prepared: Future[PreparedFrame] | None = None) -> pb.FrameAck:
        """Map one frame (``prepared`` ahead, when it was); a frame taken from a stream (with its ``record``)
        is offered to the live view."""
        try:
            result = self.mapper.process(frame if prepared is None else prepared.result(), self._time_budget)
        except Exception as error:  # the session survives a failing frame; the client sees why
            log.exception("session %s: mapping frame %d failed", self.id, frame.index)
            return messages.error_ack(frame.index, ServiceError(grpc.StatusCode.INTERNAL, f"mapping failed: {error}"))
        with self._lock:  # renders read the ledger from other threads
            self._ledger.add(sequence, frame.timestamp, len(self.mapper.keyframes) - 1 if result.keyframe else None)
            self._mapped += 1
            self._anchors, self._gaussians = result.anchors, result.gaussians
            self._last_mapped = time.monotonic()
            waiting = self._pending - 1
        refines = self.mapper.config.poses.refine
        if refines and result.pose is not None and result.pose.clamped:
            self._clamped_log.warning(f"session {self.id}: frame {frame.index}'s pose correction reached the "
                                      f"bound (poses.max_translation / max_rotation) and was clamped there")
        if record is not None:
            self.latest.offer(MappedFrame.of(frame, record, result.keyframe, result.pose if refines else None))
        return messages.frame_ack(result, sequence, time.monotonic() - received, max(waiting, 0), refines)

    # ------------------------------------------------------------------ pose corrections

    def correct_poses(self, message: pb.CorrectPosesRequest) -> pb.CorrectPosesResponse:
        """Apply a CorrectPoses batch after the frame being mapped, and record it; refusals change nothing."""
        entries = validation.pose_corrections(message, self.limits.max_pose_corrections)
        with self._mapping:
            if self._closed.is_set():
                raise ServiceError(grpc.StatusCode.NOT_FOUND, f"session_id: session {self.id} is closed")
            with self._lock:
                after = self._mapped_position.sequence
            return self._corrections.live(entries, after)

    # ------------------------------------------------------------------ queries

    def render(self, spec: validation.RenderSpec) -> Rendered:
        """At ``spec.c2w``: in the map's frame, or a client pose of the frame it names (``Mapper.render``)."""
        with self._lock:
            keyframe = self._ledger.nearest_keyframe(spec.sequence, spec.timestamp)
        return self.mapper.render(spec.c2w, spec.intrinsics, keyframe)

    def map_stats(self) -> MapStats:
        return self.mapper.stats()

    def counters(self) -> SessionCounters:
        with self._lock:
            return SessionCounters(
                received=self._received, rejected=self._rejected, mapped=self._mapped, pending=self._pending,
                skipped=self._skipped, anchors=self._anchors,
                processing_fps=rate(self._mapped, self._first_received, self._last_mapped),
                uptime_seconds=time.monotonic() - self._started,
                last_sequence=self._sequence, last_index=self._last_index,
                mapped_sequence=self._mapped_position.sequence,
            )

    def snapshot(self) -> bytes:
        return self.mapper.snapshot()

    # ------------------------------------------------------------------ end

    def close(self, timeout: float | None = None) -> bool:
        """Stop taking frames, drop the queued ones (never recorded), wait up to ``timeout`` for the
        frame being mapped, end any stream; whether the worker stopped in time."""
        with self._intake, self._lock:
            if self._closed.is_set():
                return not self._worker.is_alive()
            self._closed.set()
            self._time_budget.cancelled.set()
            sink = self._stream_sink
            dropped = sum(job is not None for job in self._jobs)
            self._jobs.clear()
            self._pending -= dropped
            self._jobs.append(None)
            self._intake.notify()
        self._worker.join(timeout)
        self._preparer.shutdown(wait=False, cancel_futures=True)
        if sink is not None:
            sink.put(SessionClosed())
        if dropped:
            log.info("session %s: closed with %d queued frames dropped", self.id, dropped)
        if self._worker.is_alive():
            log.warning("session %s: the frame being mapped did not finish within %.1f s; closing anyway",
                        self.id, timeout)
            return False
        return True
