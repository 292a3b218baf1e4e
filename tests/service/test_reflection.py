"""Server reflection answers under grpc.reflection.v1 (what current tools ask first) and v1alpha."""

from __future__ import annotations

from importlib import resources
from pathlib import Path

import pytest
from google.protobuf import descriptor_pb2
from grpc_reflection.v1alpha import reflection_pb2 as messages
from grpc_tools import protoc
from ogapi import SERVICE_NAME
from ogapi.generate import PROTO_ROOT

from .conftest import ServerHandle

# v1 and v1alpha are the same messages under two package names, hence the same bytes on the wire:
# the v1alpha classes can speak to either method.
METHODS = {
    "v1": "/grpc.reflection.v1.ServerReflection/ServerReflectionInfo",
    "v1alpha": "/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo",
}


def ask(server: ServerHandle, version: str, *requests: messages.ServerReflectionRequest) -> list:
    call = server.channel.stream_stream(
        METHODS[version], request_serializer=messages.ServerReflectionRequest.SerializeToString,
        response_deserializer=messages.ServerReflectionResponse.FromString,
    )
    return list(call(iter(requests), timeout=10))


def files(response: messages.ServerReflectionResponse) -> dict[str, descriptor_pb2.FileDescriptorProto]:
    parsed = [descriptor_pb2.FileDescriptorProto.FromString(data)
              for data in response.file_descriptor_response.file_descriptor_proto]
    return {proto.name: proto for proto in parsed}


def without_json_names(proto: descriptor_pb2.FileDescriptorProto) -> descriptor_pb2.FileDescriptorProto:
    """protoc writes each field's derived JSON name; a runtime descriptor leaves it out."""
    stack = list(proto.message_type)
    while stack:
        message = stack.pop()
        for field in message.field:
            field.ClearField("json_name")
        stack.extend(message.nested_type)
    return proto


def compiled_api(tmp_path: Path) -> descriptor_pb2.FileDescriptorProto:
    """ogapi/v1/mapping.proto as protoc compiles it from the source file."""
    out = tmp_path / "mapping.pb"
    include = resources.files("grpc_tools") / "_proto"
    assert protoc.main(["protoc", f"-I{PROTO_ROOT}", f"-I{include}", f"--descriptor_set_out={out}",
                        "ogapi/v1/mapping.proto"]) == 0
    return without_json_names(descriptor_pb2.FileDescriptorSet.FromString(out.read_bytes()).file[0])


@pytest.mark.parametrize("version", ["v1", "v1alpha"])
def test_reflection_lists_and_describes_the_api(server: ServerHandle, version: str, tmp_path: Path) -> None:
    listed, described = ask(server, version, messages.ServerReflectionRequest(list_services=""),
                            messages.ServerReflectionRequest(file_containing_symbol=SERVICE_NAME))
    names = {service.name for service in listed.list_services_response.service}
    assert {SERVICE_NAME, "grpc.health.v1.Health", "grpc.reflection.v1.ServerReflection",
            "grpc.reflection.v1alpha.ServerReflection"} <= names
    assert files(described)["ogapi/v1/mapping.proto"] == compiled_api(tmp_path)


def test_the_v1_reflection_service_describes_itself(server: ServerHandle) -> None:
    (described,) = ask(server, "v1", messages.ServerReflectionRequest(
        file_containing_symbol="grpc.reflection.v1.ServerReflection"))
    proto = files(described)["grpc/reflection/v1/reflection.proto"]
    assert proto.package == "grpc.reflection.v1"
    (method,) = proto.service[0].method
    assert (method.input_type, method.output_type) == (".grpc.reflection.v1.ServerReflectionRequest",
                                                       ".grpc.reflection.v1.ServerReflectionResponse")
    assert all(not field.type_name or field.type_name.startswith(".grpc.reflection.v1.")
               for message in proto.message_type for field in message.field)
