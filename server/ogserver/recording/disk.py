"""The server's disk: a record dir checked before serving, and write failures as statuses a client can act on.

A full disk is RESOURCE_EXHAUSTED (gRPC's own example of an exhausted resource), any other failure
to write INTERNAL. A client sees what failed and why, never a server path; the log has the path.
"""

from __future__ import annotations

import errno
import os
import tempfile
from pathlib import Path

import grpc

from ogserver.errors import ServiceError

FULL = frozenset({errno.ENOSPC, errno.EDQUOT})


class StorageError(ServiceError):
    """Writing a recording or a final snapshot failed."""


def storage_error(error: OSError, what: str) -> StorageError:
    code = grpc.StatusCode.RESOURCE_EXHAUSTED if error.errno in FULL else grpc.StatusCode.INTERNAL
    return StorageError(code, f"the server could not write {what}: {error.strerror or type(error).__name__}")


def check_writable(directory: Path) -> None:
    """Create ``directory`` if needed and write a file in it, so an unusable record dir stops the
    server at start-up (ValueError) instead of failing every CreateSession."""
    try:
        directory.mkdir(parents=True, exist_ok=True)
        descriptor, probe = tempfile.mkstemp(dir=directory, prefix=".ogserver-probe-")
        try:
            os.write(descriptor, b"ogserver")
        finally:
            os.close(descriptor)
            os.unlink(probe)
    except OSError as error:
        raise ValueError(f"record dir {directory} is not writable: {error.strerror or error}") from None
