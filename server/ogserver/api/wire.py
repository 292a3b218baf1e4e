"""Request bytes to messages, leniently: a message that does not parse is refused with INVALID_ARGUMENT.

grpcio answers a request its deserializer cannot parse with INTERNAL ("Exception deserializing
request!") and an ERROR traceback in the log, and ends a frame stream while acks of frames it
already accepted are still owed. The handlers built here parse with a deserializer that never
raises: bytes that do not parse become ``Unparsable``, which unary calls refuse before the
servicer runs, RestoreSession refuses, and StreamFrames answers with an error ack and goes on.
The log gets one throttled WARNING line for them.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import grpc
from google.protobuf.message import DecodeError
from google.protobuf.message import Message as ProtoMessage
from ogapi import SERVICE_NAME
from ogapi.v1 import mapping_pb2 as pb

from ogserver.errors import ServiceError
from ogserver.throttled_log import ThrottledLog

log = logging.getLogger(__name__)
LOG_INTERVAL_SECONDS = 10.0
_throttled = ThrottledLog(log, LOG_INTERVAL_SECONDS)

HANDLERS = {  # (client streaming, server streaming) -> grpc's handler factory
    (False, False): grpc.unary_unary_rpc_method_handler,
    (False, True): grpc.unary_stream_rpc_method_handler,
    (True, False): grpc.stream_unary_rpc_method_handler,
    (True, True): grpc.stream_stream_rpc_method_handler,
}


@dataclass(frozen=True)
class Unparsable:
    """The bytes of a request message that do not parse as its type."""

    type_name: str
    size: int

    def refusal(self) -> ServiceError:
        _throttled.warning(f"refused a request that does not parse as {self.type_name} ({self.size} bytes)")
        return ServiceError(grpc.StatusCode.INVALID_ARGUMENT,
                            f"the message does not parse as {self.type_name} ({self.size} bytes)")


def lenient(message_type: type[ProtoMessage]) -> Callable[[bytes], ProtoMessage | Unparsable]:
    def deserialize(data: bytes) -> ProtoMessage | Unparsable:
        try:
            return message_type.FromString(data)
        except DecodeError:
            return Unparsable(message_type.DESCRIPTOR.full_name, len(data))
    return deserialize


def parsed(request: Any) -> Any:
    """The request message; a ServiceError (INVALID_ARGUMENT) if it did not parse."""
    if isinstance(request, Unparsable):
        raise request.refusal()
    return request


def _refusing_unparsable(behaviour: Callable[[Any, grpc.ServicerContext], Any]) -> Callable[..., Any]:
    @functools.wraps(behaviour)
    def handle(request: Any, context: grpc.ServicerContext) -> Any:
        if isinstance(request, Unparsable):
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, request.refusal().message)
        return behaviour(request, context)
    return handle


def add_mapping_service(servicer: Any, server: grpc.Server) -> None:
    """What the generated ``add_MappingServicer_to_server`` does, with lenient request parsing."""
    handlers = {}
    for method in pb.DESCRIPTOR.services_by_name["Mapping"].methods:
        request, response = getattr(pb, method.input_type.name), getattr(pb, method.output_type.name)
        behaviour = getattr(servicer, method.name)
        if not method.client_streaming:
            behaviour = _refusing_unparsable(behaviour)
        handlers[method.name] = HANDLERS[method.client_streaming, method.server_streaming](
            behaviour, request_deserializer=lenient(request), response_serializer=response.SerializeToString
        )
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(SERVICE_NAME, handlers),))
    server.add_registered_method_handlers(SERVICE_NAME, handlers)
