"""A map's state as plain data: what defines the map, apart from how it is being optimised.

``Mapper.state()`` produces it and ``Mapper.from_state`` rebuilds a mapper from it; snapshots
(``ogmapping.persist.snapshot``) are this record written as safetensors, and anything else that stores or
moves a map (export, checkpoints, a session placed elsewhere) goes through the same two calls
rather than into the mapper's parts.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ogmapping.config import MapperConfig


@dataclass
class MapState:
    """``tensors`` are keyed ``anchors.*``, ``encoding.table``, ``decoders.*``, ``octree.*`` and
    ``trajectory.*``: anchor codes and levels (their centres follow from them), the learnable
    per-anchor tensors, the hash table (dense maps), the decoder weights, the octree's occupied
    cells and the sum of the mapped frames' camera centres (where an export bakes colour). Keyframe
    images and optimiser moments are not part of it: a map rebuilt from it renders the same
    images, and mapping continues with a fresh keyframe set and fresh Adam moments. Unless it was
    taken with ``training_state`` (a server's checkpoint): then ``training.*`` tensors hold them
    (``ogmapping.persist.training``) and a mapper rebuilt with them maps on exactly as the original."""

    config: MapperConfig
    tensors: dict[str, torch.Tensor]
    frames: int = 0
    iterations: int = 0

    def section(self, prefix: str) -> dict[str, torch.Tensor]:
        """The tensors under ``prefix.``, with the prefix removed."""
        start = f"{prefix}."
        return {name[len(start):]: value for name, value in self.tensors.items() if name.startswith(start)}
