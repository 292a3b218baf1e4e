"""Regenerate the Python code for the .proto files under proto/ (run ``make proto``).

The generated files are committed so that installing the project needs no protoc; a test
regenerates into a temporary folder and fails when the committed copies are stale.
"""

from __future__ import annotations

import argparse
import sys
from importlib import resources
from pathlib import Path

from grpc_tools import protoc

PROTO_ROOT = Path(__file__).resolve().parent.parent
PROTO_FILES = ("ogapi/v1/mapping.proto",)


def generated_names(proto_file: str) -> list[str]:
    """Paths (relative to the output root) that protoc writes for one .proto file."""
    stem = proto_file.removesuffix(".proto")
    return [f"{stem}_pb2.py", f"{stem}_pb2.pyi", f"{stem}_pb2_grpc.py"]


def generate(out_root: Path = PROTO_ROOT) -> list[Path]:
    """Run protoc (bundled with grpcio-tools) writing message, stub and type-hint modules."""
    include = resources.files("grpc_tools") / "_proto"
    for proto_file in PROTO_FILES:
        args = [
            "grpc_tools.protoc",
            f"-I{PROTO_ROOT}",
            f"-I{include}",
            f"--python_out={out_root}",
            f"--pyi_out={out_root}",
            f"--grpc_python_out={out_root}",
            proto_file,
        ]
        if protoc.main(args) != 0:
            raise RuntimeError(f"protoc failed on {proto_file}")
    return [out_root / name for proto_file in PROTO_FILES for name in generated_names(proto_file)]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=PROTO_ROOT, help="output root (default: proto/)")
    args = parser.parse_args(argv)
    for path in generate(args.out):
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
