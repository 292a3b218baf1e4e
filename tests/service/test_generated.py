"""The committed protobuf/gRPC modules must be what ``python -m ogapi.generate`` writes now."""

from __future__ import annotations

import re
from pathlib import Path

from grpc_tools.grpc_version import VERSION as GRPC_TOOLS_VERSION
from ogapi.generate import PROTO_FILES, PROTO_ROOT, generate, generated_names

DESCRIPTOR_LITERAL = re.compile(r"AddSerializedFile\((b'.*?')\)", re.DOTALL)
GENERATOR_VERSION = re.compile(r"GRPC_GENERATED_VERSION = '([^']+)'")


def test_generated_code_is_fresh(tmp_path: Path) -> None:
    """The embedded descriptors always; every byte too when the same grpcio-tools generated both."""
    generate(tmp_path)
    for proto_file in PROTO_FILES:
        names = generated_names(proto_file)
        messages = next(name for name in names if name.endswith("_pb2.py"))
        fresh = DESCRIPTOR_LITERAL.search((tmp_path / messages).read_text()).group(1)
        committed = DESCRIPTOR_LITERAL.search((PROTO_ROOT / messages).read_text()).group(1)
        assert committed == fresh, f"{messages} does not match {proto_file}: run `make proto` and commit"
        stubs = next(name for name in names if name.endswith("_pb2_grpc.py"))
        if GENERATOR_VERSION.search((PROTO_ROOT / stubs).read_text()).group(1) != GRPC_TOOLS_VERSION:
            continue  # a different generator words its output differently; the descriptor check stands
        for name in names:
            assert (PROTO_ROOT / name).read_text() == (tmp_path / name).read_text(), \
                f"{name} is stale: run `make proto` and commit the result"
