"""Morton (Z-order) codes of integer cell coordinates, vectorised over int64 tensors.

Each axis keeps 21 bits, interleaved into a 63-bit key (x in bit 0, y in bit 1, z in bit 2, ...),
so keys are non-negative int64 and sorting them walks cells in Z-order: the 8 cells of any aligned
2x2x2 block get consecutive codes. Signed coordinates are shifted by 2^20 before interleaving, so
the representable range is [-2^20, 2^20) per axis (about +-105 km at 0.1 m cells).
"""

from __future__ import annotations

import torch

BITS_PER_AXIS = 21
COORD_OFFSET = 1 << (BITS_PER_AXIS - 1)
COORD_MIN = -COORD_OFFSET
COORD_MAX = COORD_OFFSET - 1  # inclusive

# (shift, mask) steps that spread 21 low bits two zeros apart; run backwards they compact them again.
_SPREAD_STEPS = (
    (32, 0x001F00000000FFFF),
    (16, 0x001F0000FF0000FF),
    (8, 0x100F00F00F00F00F),
    (4, 0x10C30C30C30C30C3),
    (2, 0x1249249249249249),
)
_AXIS_MASK = (1 << BITS_PER_AXIS) - 1


def _spread(values: torch.Tensor) -> torch.Tensor:
    """Insert two zero bits after each of the 21 low bits."""
    values = values & _AXIS_MASK
    for shift, mask in _SPREAD_STEPS:
        values = (values | (values << shift)) & mask
    return values


def _compact(values: torch.Tensor) -> torch.Tensor:
    """Inverse of ``_spread``: gather every third bit back into the low 21 bits."""
    masks = (_AXIS_MASK, *(mask for _, mask in _SPREAD_STEPS[:-1]))
    values = values & _SPREAD_STEPS[-1][1]
    for (shift, _), mask in zip(reversed(_SPREAD_STEPS), reversed(masks), strict=True):
        values = (values | (values >> shift)) & mask
    return values


def encode(coords: torch.Tensor, checked: bool = True) -> torch.Tensor:
    """Morton codes (M,) of signed integer cell coordinates (M, 3); out-of-range raises ValueError.
    ``checked=False`` skips the range test (it makes the host wait for the device), for coordinates
    known to be in range: out-of-range ones then get wrong codes, not an error."""
    if coords.ndim != 2 or coords.shape[1] != 3:
        raise ValueError(f"coords must have shape (M, 3), got {tuple(coords.shape)}")
    if coords.is_floating_point() or coords.is_complex():
        raise ValueError(f"coords must be integers, got {coords.dtype}")
    coords = coords.to(torch.int64)
    if checked and coords.numel() and bool(((coords < COORD_MIN) | (coords > COORD_MAX)).any()):
        raise ValueError(f"cell coordinates must lie in [{COORD_MIN}, {COORD_MAX}]")
    shifted = coords + COORD_OFFSET
    return _spread(shifted[:, 0]) | (_spread(shifted[:, 1]) << 1) | (_spread(shifted[:, 2]) << 2)


def decode(codes: torch.Tensor, checked: bool = True) -> torch.Tensor:
    """Signed cell coordinates (M, 3) of Morton codes (M,); negative codes raise ValueError, unless
    ``checked=False`` (codes known to be valid, such as an octree's own: the test makes the host wait)."""
    if codes.ndim != 1:
        raise ValueError(f"codes must be one-dimensional, got shape {tuple(codes.shape)}")
    codes = codes.to(torch.int64)
    if checked and codes.numel() and bool((codes < 0).any()):
        raise ValueError("Morton codes must be non-negative")
    axes = [_compact(codes >> axis) for axis in range(3)]
    return torch.stack(axes, dim=-1) - COORD_OFFSET


def cell_coords(points: torch.Tensor, cell_size: float, checked: bool = True) -> torch.Tensor:
    """Integer coordinates (M, 3) of the cells of size ``cell_size`` holding each point (floor);
    non-finite points raise ValueError unless ``checked=False`` (then their coordinates are meaningless)."""
    if cell_size <= 0:
        raise ValueError(f"cell_size must be positive, got {cell_size}")
    scaled = torch.floor(points / cell_size)
    if checked and scaled.numel() and not bool(torch.isfinite(scaled).all()):
        raise ValueError("points must be finite")
    return scaled.to(torch.int64)
