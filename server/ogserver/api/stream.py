"""StreamFrames: a reader thread validates and queues frames while the call yields acks.

A frame that does not parse or fails validation is answered with an error ack (``accepted`` false,
``error`` set) and the stream goes on; the response stream ends once the client has half-closed and
every accepted frame has been acknowledged. The reader, the session's worker and gRPC's cancellation
callback post typed events (``sessions/stream_events.py``) to one queue, which the call reads in order.
"""

from __future__ import annotations

import logging
import queue
import threading
from collections.abc import Iterable, Iterator
from typing import assert_never

import grpc
from ogapi.v1 import mapping_pb2 as pb

from ogserver.api import messages, wire
from ogserver.errors import ServiceError
from ogserver.sessions.hosting import HostedSession
from ogserver.sessions.stream_events import Acked, Cancelled, Lost, ReaderDone, Rejected, SessionClosed, StreamEvent

log = logging.getLogger(__name__)


Requests = Iterable[pb.Frame | wire.Unparsable]


def _read(session: HostedSession, requests: Requests, sink: queue.SimpleQueue[StreamEvent], max_pixels: int) -> None:
    accepted, error = 0, None
    try:
        for request in requests:
            index = 0 if isinstance(request, wire.Unparsable) else request.index  # unknown when it does not parse
            try:
                message = wire.parsed(request)
                if not session.offer(message, max_pixels, sink):
                    error = ServiceError(grpc.StatusCode.ABORTED, "the session was closed during the stream")
                    break
            except ServiceError as refusal:
                if refusal.code == grpc.StatusCode.UNAVAILABLE:  # the session's host failed, not the frame
                    error = refusal
                    break
                session.count_rejected()
                sink.put(Rejected(messages.error_ack(index, refusal)))
                continue
            accepted += 1
    except ServiceError as refusal:  # the client sent nothing for the stream idle timeout
        error = refusal
    except grpc.RpcError as failure:  # a cancelled call ends its request iterator with an error
        log.debug("session %s: frame stream ended: %s", session.id, failure)
    except Exception:  # a defect, not the client: never end a stream silently
        log.exception("session %s: reading the frame stream failed", session.id)
        error = ServiceError(grpc.StatusCode.INTERNAL, "the server failed while reading the frame stream")
    finally:
        sink.put(ReaderDone(accepted, error))


def serve(
    session: HostedSession, requests: Requests, context: grpc.ServicerContext, max_pixels: int
) -> Iterator[pb.FrameAck]:
    sink: queue.SimpleQueue[StreamEvent] = queue.SimpleQueue()
    with session.stream(sink):
        context.add_callback(lambda: sink.put(Cancelled()))
        reader = threading.Thread(
            target=_read, args=(session, requests, sink, max_pixels), name=f"stream-{session.id[:8]}", daemon=True
        )
        reader.start()
        done: ReaderDone | None = None
        acked = 0
        while done is None or acked < done.accepted:
            match sink.get():
                case Cancelled():
                    return
                case SessionClosed():
                    raise ServiceError(grpc.StatusCode.ABORTED, "the session was closed during the stream")
                case ReaderDone(error=ServiceError() as error) | Lost(error):
                    raise error
                case ReaderDone() as finished:
                    done = finished
                case Acked(ack):
                    acked += 1
                    yield ack
                case Rejected(ack):
                    yield ack
                case unexpected:
                    assert_never(unexpected)
