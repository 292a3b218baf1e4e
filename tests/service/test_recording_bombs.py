"""Hostile recordings: length fields and chunk sizes that claim far more than the file holds are refused
(or read as a cut end) before anything of that size is allocated, with one line from the client tools.

The files are built here, a few bytes to 131 KB: a zstd frame of RLE blocks inflates 32768-fold.
Python's allocations (the decompressed bytes, the bytes a read asks for) are watched with tracemalloc.
"""

from __future__ import annotations

import struct
import tracemalloc
from collections.abc import Callable
from pathlib import Path

import pytest
from mcap.data_stream import RecordBuilder
from mcap.records import Header
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer
from ogapi import recording as layout
from ogapi.mcap_records import MAX_CHUNK_BYTES
from ogapi.v1 import mapping_pb2 as pb
from ogclient.__main__ import main

MAGIC = b"\x89MCAP0\r\n"
ZSTD_MAGIC = struct.pack("<I", 0xFD2FB528)
RLE_BLOCK = 128 << 10  # zstd's largest block
CHUNK = 0x06
SMALL = 16 << 20  # bytes Python may allocate while refusing a file


def zstd_fill(size: int, content_size: bool = True) -> bytes:
    """A zstd frame of ``size`` bytes 0x7F made of RLE blocks (4 bytes each), its size in the frame
    header or not. Inflated, it reads as one record of unknown opcode as long as the rest."""
    header = bytes([0xE0]) + struct.pack("<Q", size) if content_size else bytes([0x00, 0x58])
    blocks = bytearray()
    for start in range(0, size, RLE_BLOCK):
        length = min(RLE_BLOCK, size - start)
        last = int(start + length == size)
        blocks += struct.pack("<I", last | 1 << 1 | length << 3)[:3] + b"\x7f"
    return ZSTD_MAGIC + header + bytes(blocks)


def mcap_with_chunk(data: bytes, declared: int, data_length: int | None = None, record_length: int | None = None,
                    compression: str = "zstd") -> bytes:
    """A Header and one chunk record whose fields say what the arguments say, whatever ``data`` holds."""
    header = RecordBuilder()
    Header(profile="", library="test").write(header)
    fields = (struct.pack("<QQQII", 0, 0, declared, 0, len(compression)) + compression.encode()
              + struct.pack("<Q", len(data) if data_length is None else data_length) + data)
    length = len(fields) if record_length is None else record_length
    return MAGIC + header.end() + struct.pack("<BQ", CHUNK, length) + fields


def peak_allocation(action: Callable[[], object]) -> int:
    tracemalloc.start()
    try:
        action()
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    return peak


def refused(path: Path, match: str) -> int:
    """Peak bytes allocated while ``load`` refuses ``path`` with ``match``."""

    def load() -> None:
        with pytest.raises(layout.RecordingError, match=match):
            layout.load(path)

    return peak_allocation(load)


def test_a_chunk_claiming_a_terabyte_is_refused_not_allocated(tmp_path: Path) -> None:
    path = tmp_path / "claim.mcap"
    path.write_bytes(mcap_with_chunk(zstd_fill(1 << 20, content_size=False)[:40], declared=1 << 40))
    assert path.stat().st_size < 128
    assert refused(path, r"a chunk declares 1099511627776 bytes uncompressed, over the limit of 512 MiB") < SMALL


def test_a_zstd_bomb_over_the_chunk_limit_is_never_inflated(tmp_path: Path) -> None:
    size = MAX_CHUNK_BYTES + RLE_BLOCK
    path = tmp_path / "bomb.mcap"
    path.write_bytes(mcap_with_chunk(zstd_fill(size), declared=size))
    assert path.stat().st_size < 20_000
    assert refused(path, f"a chunk declares {size} bytes uncompressed") < SMALL


def test_a_zstd_frame_larger_than_its_chunk_declares_is_never_inflated(tmp_path: Path) -> None:
    path = tmp_path / "liar.mcap"
    path.write_bytes(mcap_with_chunk(zstd_fill(64 << 20), declared=1000))
    assert refused(path, r"zstd frame holds 67108864 bytes, more than the 1000 its header declares") < SMALL
    path.write_bytes(mcap_with_chunk(zstd_fill(64 << 20, content_size=False), declared=1000))
    assert refused(path, "did not decompress full frame") < SMALL


def test_lengths_beyond_the_file_allocate_nothing_of_their_size(tmp_path: Path) -> None:
    path = tmp_path / "long.mcap"
    path.write_bytes(mcap_with_chunk(b"xx", declared=100, data_length=1 << 40))  # a consistent record around it
    assert refused(path, "not a readable recording") < SMALL
    cut = mcap_with_chunk(b"xx", declared=100, data_length=3 << 30, record_length=(3 << 30) + 64)
    path.write_bytes(cut)  # a record longer than the file: a cut end, read up to it
    peak = peak_allocation(lambda: layout.load(path))
    assert peak < SMALL


def test_the_client_tools_refuse_a_bomb_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    bomb, out = tmp_path / "bomb.mcap", tmp_path / "repaired.mcap"
    bomb.write_bytes(mcap_with_chunk(zstd_fill(4 << 30), declared=4 << 30))  # 131 KB, 4 GiB inflated
    assert main(["repair-recording", str(bomb), str(out)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"ogclient: {bomb} is not a readable recording: a chunk declares")
    assert not out.exists()


@pytest.mark.parametrize("compression", [CompressionType.ZSTD, CompressionType.LZ4, CompressionType.NONE])
def test_records_within_the_limits_are_those_mcap_reads(tmp_path: Path, compression: CompressionType) -> None:
    path = tmp_path / "fine.mcap"
    with open(path, "wb") as stream:
        writer = Writer(stream, compression=compression, chunk_size=4096)
        writer.start(profile="", library="test")
        schema = writer.register_schema("ogapi.v1.Frame", "protobuf", b"")
        channel = writer.register_channel(layout.TOPIC_FRAMES, "protobuf", schema)
        for index in range(40):
            frame = pb.Frame(index=index, timestamp=index * 0.1)
            frame.color.data = bytes([index]) * 1000
            writer.add_message(channel, log_time=index, data=frame.SerializeToString(), publish_time=index)
        writer.finish()
    with open(path, "rb") as stream:
        expected = [(r.log_time, r.data) for r in StreamReader(stream, validate_crcs=True).records
                    if type(r).__name__ == "Message"]
    assert [(m.log_time_ns, m.data) for m in layout.read_messages(path)] == expected
    assert len(expected) == 40
