"""The ogapi.v1.Mapping servicer: translate calls to registry/session operations and errors to statuses."""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Iterable, Iterator
from contextlib import contextmanager

import grpc
from ogapi import SESSION_METADATA_KEY, TOKEN_METADATA_KEY
from ogapi.v1 import mapping_pb2 as pb
from ogapi.v1 import mapping_pb2_grpc as pb_grpc

from ogserver import messages, stream, validation, wire
from ogserver.errors import ServiceError, exhausted, invalid
from ogserver.registry import Registry
from ogserver.session import Session

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


def credentials(session: Session) -> pb.SessionCredentials:
    return messages.credentials(session.config, session.token, session.recorder.path)


def info(session: Session) -> pb.SessionInfo:
    return messages.session_info(session.config, session.counters(), session.streaming, session.recorder.path)


class MappingService(pb_grpc.MappingServicer):
    def __init__(self, registry: Registry) -> None:
        self.registry = registry
        self.limits = registry.settings.limits

    def _session(self, session_id: str, context: grpc.ServicerContext) -> Session:
        return self.registry.get(session_id, metadata(context, TOKEN_METADATA_KEY))

    def CreateSession(self, request: pb.CreateSessionRequest, context: grpc.ServicerContext) -> pb.SessionCredentials:
        with status_errors(context):
            return credentials(self.registry.create(request))

    def StreamFrames(
        self, request_iterator: Iterable[pb.Frame], context: grpc.ServicerContext
    ) -> Iterator[pb.FrameAck]:
        with status_errors(context):
            session_id = metadata(context, SESSION_METADATA_KEY)
            if not session_id:
                raise invalid(SESSION_METADATA_KEY, "metadata is required for StreamFrames")
            session = self.registry.get(session_id, metadata(context, TOKEN_METADATA_KEY), SESSION_METADATA_KEY)
            yield from stream.serve(session, request_iterator, context, self.limits.max_image_pixels)

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
            data = self._session(request.session_id, context).snapshot()
            yield from messages.snapshot_chunks(data, min(SNAPSHOT_CHUNK_BYTES, self.limits.max_message_bytes // 2))

    def RestoreSession(
        self, request_iterator: Iterable[pb.RestoreChunk], context: grpc.ServicerContext
    ) -> pb.SessionCredentials:
        with status_errors(context):
            parts: list[bytes] = []
            total, label, first = 0, "", True
            for chunk in map(wire.parsed, request_iterator):
                if first:
                    label, first = chunk.label, False
                total += len(chunk.data)
                if total > self.limits.max_snapshot_bytes:
                    limit = self.limits.max_snapshot_bytes
                    raise exhausted("data", f"the snapshot is larger than the server limit of {limit} bytes")
                parts.append(chunk.data)
            data = b"".join(parts)
            if not data:
                raise invalid("data", "no snapshot bytes received")
            return credentials(self.registry.restore(data, label, hashlib.sha256(data).hexdigest()))

    def ListSessions(self, request: pb.ListSessionsRequest, context: grpc.ServicerContext) -> pb.ListSessionsResponse:
        with status_errors(context):
            return pb.ListSessionsResponse(sessions=[info(session) for session in self.registry.sessions()])

    def CloseSession(self, request: pb.CloseSessionRequest, context: grpc.ServicerContext) -> pb.CloseSessionResponse:
        with status_errors(context):
            closed = self.registry.close(self._session(request.session_id, context))
            return pb.CloseSessionResponse(
                stats=closed.stats, recording=str(closed.recording),
                snapshot=str(closed.snapshot) if closed.snapshot else "",
            )
