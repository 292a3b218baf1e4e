"""Checks that a refusal names what it refuses as mapping.proto spells it (fields, metadata, enums)."""

from __future__ import annotations

import re

from google.protobuf.descriptor import Descriptor
from ogapi import API_KEY_METADATA_KEY, SESSION_METADATA_KEY, TOKEN_METADATA_KEY
from ogapi.v1 import mapping_pb2 as pb

ENUM_VALUES = {value.name for enum in pb.DESCRIPTOR.enum_types_by_name.values() for value in enum.values}
# Upper-case words with an underscore are enum-value names (JPEG and PNG alone name file formats).
ENUM_LIKE = re.compile(r"\b[A-Z][A-Z0-9]*_[A-Z0-9_]+\b")
# "name: reason": a field path or metadata key, no spaces, before the first ": ".
NAMED = re.compile(r"^([A-Za-z0-9_.-]+): ")
METADATA_KEYS = {SESSION_METADATA_KEY, TOKEN_METADATA_KEY, API_KEY_METADATA_KEY}


def assert_spelled_as_the_proto(message: str, request: Descriptor, named: bool = True) -> None:
    """A refusal of ``request`` that starts with a field path of it (or a metadata key), when
    ``named``; either way, enum values are named as in the .proto."""
    match = NAMED.match(message)
    assert match or not named, f"no field path in {message!r}"
    if match and match.group(1) not in METADATA_KEYS:
        path = match.group(1)
        descriptor: Descriptor | None = request
        for part in path.split("."):
            assert descriptor is not None and part in descriptor.fields_by_name, \
                f"{path!r} is not a {request.name} field"
            descriptor = descriptor.fields_by_name[part].message_type
    unknown = set(ENUM_LIKE.findall(message)) - ENUM_VALUES
    assert not unknown, f"{message!r} names {unknown}, which the .proto does not define"
