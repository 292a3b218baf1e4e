"""Snapshots: a ``MapState`` as safetensors bytes (no pickle), with its config and a format version.

Anchor centres are stored (a pose correction moves anchors off their cells' centres); snapshots written
before that hold none, and their anchors sit at the centres their Morton codes and levels give. The
learnable per-anchor tensors and the hash table are stored in float16 (their values are small and
a float16 round trip changes renders by far less than a display level); decoder weights stay
float32. A server's checkpoints, from which a session goes on mapping, keep them in float32
(``half=False``). What is not in a ``MapState`` (keyframes, optimiser moments) is not in a snapshot.
"""

from __future__ import annotations

import json

import torch
from safetensors.torch import load as load_tensors
from safetensors.torch import save as save_tensors

from ogmapping.config import ConfigBounds, MapperConfig
from ogmapping.persist.state import MapState

FORMAT = "ogmapping-snapshot"
VERSION = "1"
HALF = ("anchors.log_scales", "anchors.offsets", "anchors.features", "anchors.colours", "encoding.table")


def encode(state: MapState, half: bool = True) -> bytes:
    """The snapshot bytes of ``state``; ``half``: the ``HALF`` tensors in float16."""
    tensors = {
        name: (value.to(torch.float16) if half and name in HALF else value).detach().cpu().contiguous()
        for name, value in state.tensors.items()
    }
    metadata = {
        "format": FORMAT,
        "version": VERSION,
        "config": json.dumps(state.config.to_dict()),
        "frames": str(state.frames),
        "iterations": str(state.iterations),
    }
    return save_tensors(tensors, metadata=metadata)


def read_metadata(data: bytes) -> dict[str, str]:
    """The metadata block of a safetensors file, validated as one of our snapshots."""
    if len(data) < 8:
        raise ValueError("snapshot is truncated (shorter than its 8-byte header length)")
    header_length = int.from_bytes(data[:8], "little")
    if header_length <= 0 or 8 + header_length > len(data):
        raise ValueError("snapshot header length is out of range: the data is truncated or not a snapshot")
    try:
        header = json.loads(data[8 : 8 + header_length])
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ValueError(f"snapshot header is not valid JSON: {error}") from error
    metadata = header.get("__metadata__") or {}
    if metadata.get("format") != FORMAT:
        raise ValueError("data is not an ogmapping snapshot (format tag missing)")
    if metadata.get("version") != VERSION:
        raise ValueError(f"snapshot version {metadata.get('version')!r} is not supported (expected {VERSION})")
    return metadata


def decode(data: bytes, bounds: ConfigBounds | None = None) -> MapState:
    """The ``MapState`` in snapshot bytes (float32 again); raises ValueError on anything malformed,
    and on a config beyond ``bounds`` before any tensor is loaded."""
    metadata = read_metadata(data)
    try:
        frames, iterations = int(metadata.get("frames", 0)), int(metadata.get("iterations", 0))
        config = MapperConfig.from_dict(json.loads(metadata["config"]))
    except (KeyError, ValueError, TypeError, AttributeError) as error:
        raise ValueError(f"snapshot metadata is malformed: {error}") from error
    if bounds is not None:
        bounds.check(config)
    try:
        tensors = load_tensors(data)
    except Exception as error:  # safetensors raises its own error types for corrupt payloads
        raise ValueError(f"snapshot payload is corrupt: {error}") from error
    tensors = {name: value.float() if name in HALF else value for name, value in tensors.items()}
    return MapState(config, tensors, frames, iterations)
