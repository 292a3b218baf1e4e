"""Server reflection under both names tools ask for: ``grpc.reflection.v1`` and ``v1alpha``.

grpcio-reflection (1.85) serves only ``grpc.reflection.v1alpha``; grpcurl, Postman and current gRPC
libraries ask for ``grpc.reflection.v1`` first. The two protocols are the same messages under
another package name, so they are the same bytes on the wire: the v1 service is the library's
servicer registered under the v1 method name, and the v1 descriptor (which ListServices and
``file_containing_symbol`` must be able to describe) is the v1alpha file renamed.
"""

from __future__ import annotations

import grpc
from google.protobuf import descriptor_pb2, descriptor_pool
from grpc_reflection.v1alpha import _async, reflection
from grpc_reflection.v1alpha import reflection_pb2 as v1alpha

V1ALPHA_PACKAGE = "grpc.reflection.v1alpha"
V1_PACKAGE = "grpc.reflection.v1"
V1_FILE = "grpc/reflection/v1/reflection.proto"
V1_SERVICE_NAME = f"{V1_PACKAGE}.ServerReflection"
V1ALPHA_SERVICE_NAME = reflection.SERVICE_NAME


def v1_file_descriptor() -> descriptor_pb2.FileDescriptorProto:
    """The v1alpha reflection file with its package, file name and type references renamed to v1."""
    proto = descriptor_pb2.FileDescriptorProto()
    v1alpha.DESCRIPTOR.CopyToProto(proto)
    proto.name, proto.package = V1_FILE, V1_PACKAGE
    proto.ClearField("options")
    old, new = f".{V1ALPHA_PACKAGE}.", f".{V1_PACKAGE}."
    for message in proto.message_type:
        for field in message.field:
            if field.type_name.startswith(old):
                field.type_name = new + field.type_name[len(old):]
    for service in proto.service:
        for method in service.method:
            method.input_type = new + method.input_type[len(old):]
            method.output_type = new + method.output_type[len(old):]
    return proto


def register_v1_descriptor(pool: descriptor_pool.DescriptorPool) -> None:
    """Make ``grpc.reflection.v1`` describable from ``pool`` (once; later calls do nothing)."""
    try:
        pool.FindFileByName(V1_FILE)
    except KeyError:
        pool.Add(v1_file_descriptor())


def enable(server: grpc.aio.Server, service_names: tuple[str, ...]) -> None:
    """Serve reflection for ``service_names`` (and both reflection services) on ``server``."""
    register_v1_descriptor(descriptor_pool.Default())
    names = (*service_names, V1_SERVICE_NAME, V1ALPHA_SERVICE_NAME)
    servicer = _async.ReflectionServicer(names)  # the library's servicer for grpc.aio servers
    method = grpc.stream_stream_rpc_method_handler(
        servicer.ServerReflectionInfo,
        request_deserializer=v1alpha.ServerReflectionRequest.FromString,
        response_serializer=v1alpha.ServerReflectionResponse.SerializeToString,
    )
    handlers = {"ServerReflectionInfo": method}
    for service in (V1_SERVICE_NAME, V1ALPHA_SERVICE_NAME):
        server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(service, handlers),))
