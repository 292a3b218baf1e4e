"""Plain values to message fields: how frames are packed, and 4x4 matrices as 16 numbers.

Nothing here names an engine type; turning engine frames and intrinsics into messages is the
client's (``ogclient.messages``), so ``ogapi`` stays importable without the engine.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ogapi.v1 import mapping_pb2 as pb


@dataclass(frozen=True)
class FrameEncoding:
    """How a client packs frames; PNG colour and millimetre PNG depth lose nothing for 8-bit/mm data."""

    color: int = pb.COLOR_PNG
    depth: int = pb.DEPTH_PNG16
    depth_scale: float = 1000.0
    jpeg_quality: int = 95


def matrix_to_list(matrix: np.ndarray) -> list[float]:
    """4x4 matrix as 16 row-major numbers."""
    return [float(v) for v in np.asarray(matrix, dtype=np.float64).reshape(16)]
