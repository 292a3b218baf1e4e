"""The ogapi.v1.Mapping servicer: translate calls to registry/session operations and errors to statuses."""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager

import grpc
from ogapi import API_KEY_METADATA_KEY, SESSION_METADATA_KEY, TOKEN_METADATA_KEY
from ogapi.v1 import mapping_pb2 as pb
from ogapi.v1 import mapping_pb2_grpc as pb_grpc

from ogserver.access.callers import Callers
from ogserver.access.failed_auth import FailedAuthentications, peer_address
from ogserver.access.shares import Shares
from ogserver.api import messages, stream, validation, wire
from ogserver.api.pacing import Paced, Timeout
from ogserver.errors import ServiceError, exhausted, invalid
from ogserver.metrics import Metrics
from ogserver.sessions.hosting import HostedSession, Opened, SessionHost, Upload

log = logging.getLogger(__name__)
SNAPSHOT_CHUNK_BYTES = 1 << 20


@contextmanager
def status_errors(context: grpc.ServicerContext) -> Iterator[None]:
    """End the call with the refusal's status, or INTERNAL (logged) for anything unexpected."""
    try:
        yield
    except ServiceError as error:
        context.abort(error.code, error.message)
    except Exception as error:
        log.exception("unexpected failure")
        context.abort(grpc.StatusCode.INTERNAL, f"server error: {error}")


def metadata(context: grpc.ServicerContext, key: str) -> str:
    for name, value in context.invocation_metadata() or ():
        if name == key:
            return value if isinstance(value, str) else value.decode()
    return ""


def credentials(opened: Opened) -> pb.SessionCredentials:
    return messages.credentials(opened.session.config, opened.token, opened.session.recording)


def info(session: HostedSession) -> pb.SessionInfo:
    return messages.session_info(session.config, session.counters(), session.streaming, session.recording)


def infos(sessions: Iterable[HostedSession]) -> list[pb.SessionInfo]:
    """Each listed session's info, leaving out one that closed or expired while it was being listed (a worker
    process answers NOT_FOUND for it)."""
    listed = []
    for session in sessions:
        try:
            listed.append(info(session))
        except ServiceError as error:
            if error.code != grpc.StatusCode.NOT_FOUND:
                raise
    return listed


class MappingService(pb_grpc.MappingServicer):
    def __init__(self, registry: SessionHost, callers: Callers, metrics: Metrics) -> None:
        self.registry = registry
        self.callers = callers
        self.metrics = metrics
        self.limits = registry.settings.limits
        self.access = registry.settings.access
        self.failures = FailedAuthentications(self.access.max_auth_failures, self.access.auth_failure_window_seconds,
                                              self.access.max_auth_failures_total)
        self.snapshots = Shares(self.limits.max_snapshots_per_session)  # GetSnapshot calls per session

    def _caller(self, context: grpc.ServicerContext) -> str:
        """Who creates, restores or lists: refused (and counted against the address) when unknown."""
        with self.failures.guard(peer_address(context.peer())):
            return self.callers.identify(metadata(context, API_KEY_METADATA_KEY), context.peer_identities())

    def _session(self, session_id: str, context: grpc.ServicerContext, field: str = "session_id") -> HostedSession:
        with self.failures.guard(peer_address(context.peer())):
            return self.registry.get(session_id, metadata(context, TOKEN_METADATA_KEY), field)

    def CreateSession(self, request: pb.CreateSessionRequest, context: grpc.ServicerContext) -> pb.SessionCredentials:
        with status_errors(context):
            return credentials(self.registry.create(request, self._caller(context)))

    def StreamFrames(
        self, request_iterator: Iterable[pb.Frame], context: grpc.ServicerContext
    ) -> Iterator[pb.FrameAck]:
        with status_errors(context):
            session_id = metadata(context, SESSION_METADATA_KEY)
            if not session_id:
                raise invalid(SESSION_METADATA_KEY, "metadata is required for StreamFrames")
            session = self._session(session_id, context, SESSION_METADATA_KEY)
            requests = Paced(request_iterator, Timeout(self.access.stream_idle_seconds, "stream_idle_seconds"))
            try:
                for ack in stream.serve(session, requests, context, self.limits.max_image_pixels):
                    self.metrics.ack(ack)
                    yield ack
            finally:
                requests.close()
                self.registry.touch(session)

    def Render(self, request: pb.RenderRequest, context: grpc.ServicerContext) -> pb.RenderResponse:
        with status_errors(context):
            session = self._session(request.session_id, context)
            spec = validation.render_request(request, self.limits.max_image_pixels)
            start = time.perf_counter()
            response = messages.render_response(spec, session.render(spec))
            response.render_seconds = time.perf_counter() - start
            return response

    def GetStats(self, request: pb.GetStatsRequest, context: grpc.ServicerContext) -> pb.Stats:
        with status_errors(context):
            session = self._session(request.session_id, context)
            return messages.stats(session.config, session.map_stats(), session.counters())

    def GetSnapshot(self, request: pb.GetSnapshotRequest, context: grpc.ServicerContext) -> Iterator[pb.SnapshotChunk]:
        with status_errors(context):
            session = self._session(request.session_id, context)
            if not self.snapshots.take(request.session_id):
                raise exhausted("session_id", f"this session has {self.snapshots.limit} GetSnapshot calls running "
                                              f"(the server's limits.max_snapshots_per_session); retry when one ends")
            try:
                data = session.snapshot()
                yield from messages.snapshot_chunks(data, min(SNAPSHOT_CHUNK_BYTES, self.limits.max_message_bytes // 2))
            finally:
                self.snapshots.give_back(request.session_id)

    def RestoreSession(
        self, request_iterator: Iterable[pb.RestoreChunk], context: grpc.ServicerContext
    ) -> pb.SessionCredentials:
        with status_errors(context):
            owner = self._caller(context)
            chunks = Paced(map(wire.parsed, request_iterator),
                           Timeout(self.access.restore_idle_seconds, "restore_idle_seconds"),
                           Timeout(self.access.restore_seconds, "restore_seconds"))
            try:
                return credentials(self.registry.restore(owner, lambda: self._receive(chunks)))
            finally:
                chunks.close()

    def _receive(self, chunks: Iterator[pb.RestoreChunk]) -> Upload:
        """The snapshot's bytes, refused as soon as the label or the size is over its limit."""
        parts: list[bytes] = []
        total, label, first = 0, "", True
        for chunk in chunks:
            if first:
                label, first = chunk.label, False
                self.registry.check_label(label)
            total += len(chunk.data)
            if total > self.limits.max_snapshot_bytes:
                limit = self.limits.max_snapshot_bytes
                raise exhausted("data", f"the snapshot is larger than the server limit of {limit} bytes")
            parts.append(chunk.data)
        data = b"".join(parts)
        if not data:
            raise invalid("data", "no snapshot bytes received")
        return Upload(data, label, hashlib.sha256(data).hexdigest())

    def ListSessions(self, request: pb.ListSessionsRequest, context: grpc.ServicerContext) -> pb.ListSessionsResponse:
        with status_errors(context):
            owned = self.registry.sessions(self._caller(context))
            return pb.ListSessionsResponse(sessions=infos(owned))

    def CorrectPoses(self, request: pb.CorrectPosesRequest, context: grpc.ServicerContext) -> pb.CorrectPosesResponse:
        with status_errors(context):
            return self._session(request.session_id, context).correct_poses(request)

    def CloseSession(self, request: pb.CloseSessionRequest, context: grpc.ServicerContext) -> pb.CloseSessionResponse:
        with status_errors(context):
            closed = self.registry.close(self._session(request.session_id, context))
            return messages.closed(closed.stats, closed.recording, closed.snapshot)
