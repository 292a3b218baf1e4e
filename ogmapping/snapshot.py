"""Snapshots: the map as safetensors bytes (no pickle), with its config and a format version.

Anchor centres are not stored: they follow exactly from each anchor's Morton code and level. The
learnable per-anchor tensors and the hash table are stored in float16 (their values are small and
a float16 round trip changes renders by far less than a display level); decoder weights stay
float32. Keyframe images and optimiser moments are not stored: a restored map renders the same
images, and mapping continues with a fresh keyframe set and fresh Adam moments.
"""

from __future__ import annotations

import json

import torch
from safetensors.torch import load as load_tensors
from safetensors.torch import save as save_tensors

from ogmapping.config import MapperConfig

FORMAT = "ogmapping-snapshot"
VERSION = "1"
HALF = ("anchors.log_scales", "anchors.offsets", "anchors.features", "encoding.table")


def dump(mapper) -> bytes:
    """Serialise a ``Mapper``."""
    tensors: dict[str, torch.Tensor] = {
        "anchors.codes": mapper.anchors.codes,
        "anchors.levels": mapper.anchors.levels,
        "anchors.log_scales": mapper.anchors.log_scales.detach(),
        "anchors.offsets": mapper.anchors.offsets.detach(),
        "anchors.spawned": mapper.anchors.spawned.to(torch.uint8),
        "anchors.observations": mapper.anchors.observations,
    }
    if mapper.anchors.with_features:
        tensors["anchors.features"] = mapper.anchors.features.detach()
    if mapper.encoding is not None:
        tensors["encoding.table"] = mapper.encoding.table.detach()
    for name, value in mapper.decoders.state_dict().items():
        tensors[f"decoders.{name}"] = value
    for name, value in mapper.octree.state_dict().items():
        tensors[f"octree.{name}"] = value
    tensors = {
        name: (value.to(torch.float16) if name in HALF else value).detach().cpu().contiguous()
        for name, value in tensors.items()
    }
    metadata = {
        "format": FORMAT,
        "version": VERSION,
        "config": json.dumps(mapper.config.to_dict()),
        "frames": str(mapper.frames),
        "iterations": str(mapper.iterations),
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


def load(data: bytes, device: str | torch.device = "cpu"):
    """Rebuild a ``Mapper`` from ``dump`` bytes; raises ValueError on anything malformed."""
    from ogmapping.mapper import Mapper

    metadata = read_metadata(data)
    try:
        tensors = load_tensors(data)
    except Exception as error:  # safetensors raises its own error types for corrupt payloads
        raise ValueError(f"snapshot payload is corrupt: {error}") from error
    config = MapperConfig.from_dict(json.loads(metadata["config"]))
    mapper = Mapper(config, device)
    try:
        _fill(mapper, tensors)
    except (KeyError, RuntimeError) as error:
        raise ValueError(f"snapshot does not match its config: {error}") from error
    mapper.frames = int(metadata.get("frames", 0))
    mapper.iterations = int(metadata.get("iterations", 0))
    return mapper


def _fill(mapper, tensors: dict[str, torch.Tensor]) -> None:
    device = mapper.device
    mapper.octree.load_state_dict({k[len("octree."):]: v for k, v in tensors.items() if k.startswith("octree.")})
    mapper.octree.device = device
    decoder_state = {k[len("decoders."):]: v for k, v in tensors.items() if k.startswith("decoders.")}
    mapper.decoders.load_state_dict(decoder_state)
    if mapper.encoding is not None:
        mapper.encoding.table.data.copy_(tensors["encoding.table"].to(torch.float32))
    codes = tensors["anchors.codes"].to(device)
    levels = tensors["anchors.levels"].to(device)
    positions = mapper.octree.centers_by_level(codes, levels)
    anchors = mapper.anchors
    features = tensors["anchors.features"].float() if anchors.with_features else None
    anchors.add(codes, levels, positions, torch.ones(codes.numel(), device=device), features, mapper.optimizer)
    anchors.log_scales.data.copy_(tensors["anchors.log_scales"].float())
    anchors.offsets.data.copy_(tensors["anchors.offsets"].float())
    anchors.spawned = tensors["anchors.spawned"].to(device).bool()
    anchors.observations = tensors["anchors.observations"].to(device)
