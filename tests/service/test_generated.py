"""The committed protobuf/gRPC modules must be what ``python -m ogapi.generate`` writes now."""

from __future__ import annotations

from pathlib import Path

from ogapi.generate import PROTO_FILES, PROTO_ROOT, generate, generated_names


def test_generated_code_is_fresh(tmp_path: Path) -> None:
    written = generate(tmp_path)
    assert written
    for proto_file in PROTO_FILES:
        for name in generated_names(proto_file):
            fresh = (tmp_path / name).read_text()
            committed = (PROTO_ROOT / name).read_text()
            assert committed == fresh, f"{name} is stale: run `make proto` and commit the result"
