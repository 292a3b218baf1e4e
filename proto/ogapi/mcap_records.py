"""MCAP records read with memory bounded by the file and by a cap on a chunk's size.

``mcap.StreamReader`` trusts length fields: it asks the file for as many bytes as a record says it
holds (a 118-byte file claiming a 1 TiB chunk ends in a ``MemoryError``) and inflates a chunk to
whatever size its header or its zstd frame declares (a 131 KB file inflates to 4 GiB). Here reads
never ask for more than the file has left, and a chunk is opened only when the size its header
declares is within ``MAX_CHUNK_BYTES`` and its compressed data cannot inflate past that size. The
records and their bytes are those ``StreamReader`` yields for any file within these bounds.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Iterator
from typing import BinaryIO

import zstandard
from mcap.records import Chunk, McapRecord
from mcap.stream_reader import StreamReader, breakup_chunk

try:
    import lz4.frame as lz4
except ImportError:  # optional in mcap too: a recording the server writes is zstd
    lz4 = None

# A recording's chunk holds about one frame (the writer closes a chunk past 1 MiB, and the server
# flushes one a frame): far above the client's 256 MiB message limit, far below a bomb's gigabytes.
MAX_CHUNK_BYTES = 512 << 20


class _FileReads:
    """A file whose reads ask for no more than it holds, so a length field claiming more costs no
    allocation of that length (a read past the end is short, as it always was)."""

    def __init__(self, stream: BinaryIO) -> None:
        self._stream = stream
        self._size = os.fstat(stream.fileno()).st_size

    def read(self, size: int = -1) -> bytes:
        position = self._stream.tell()
        if size >= 0 and position + size > self._size:
            self._size = os.fstat(self._stream.fileno()).st_size  # a file still being written grows
            size = min(size, max(self._size - position, 0))
        return self._stream.read(size)


def opened(chunk: Chunk, max_bytes: int = MAX_CHUNK_BYTES) -> Chunk:
    """The chunk with its data inflated; ValueError, before any large allocation, for one that declares
    more than ``max_bytes`` or whose data inflates past what it declares. Other compressions are left
    as they are, for mcap to read as it does (uncompressed) or refuse (lz4 where it is not installed)."""
    if chunk.compression not in ("zstd", "lz4") or (chunk.compression == "lz4" and lz4 is None):
        return chunk
    declared = chunk.uncompressed_size
    if declared > max_bytes:
        raise ValueError(f"a chunk declares {declared} bytes uncompressed, over the limit of {max_bytes >> 20} MiB")
    if chunk.compression == "zstd":
        framed = zstandard.frame_content_size(chunk.data)
        if framed > declared:
            raise ValueError(f"a chunk's zstd frame holds {framed} bytes, more than the {declared} its header declares")
        data = zstandard.decompress(chunk.data, declared)  # without a frame size, at most ``declared``
    else:
        decompressor = lz4.LZ4FrameDecompressor()
        data = decompressor.decompress(chunk.data, max_length=declared)
        if not decompressor.eof:
            raise ValueError(f"a chunk's lz4 data is cut or holds more than the {declared} bytes its header declares")
    return dataclasses.replace(chunk, compression="", data=data)


def records(stream: BinaryIO, validate_crcs: bool = True) -> Iterator[McapRecord]:
    """The file's records in order, chunks opened (their records in place of the chunk)."""
    for record in StreamReader(_FileReads(stream), validate_crcs=validate_crcs, emit_chunks=True).records:
        if isinstance(record, Chunk):
            yield from breakup_chunk(opened(record), validate_crc=validate_crcs)
        else:
            yield record
