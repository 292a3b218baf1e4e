"""Morton codes: exact round trip over the whole signed range, Z-order, and range errors."""

from __future__ import annotations

import pytest
import torch

from ogmapping.structure import morton


def interleave(x: int, y: int, z: int) -> int:
    """Brute-force bit interleave of offset coordinates, the definition the vectorised code must match."""
    code = 0
    for bit in range(morton.BITS_PER_AXIS):
        for axis, value in enumerate((x, y, z)):
            code |= ((value + morton.COORD_OFFSET) >> bit & 1) << (3 * bit + axis)
    return code


def test_round_trip_random_and_extremes() -> None:
    generator = torch.Generator().manual_seed(0)
    random = torch.randint(morton.COORD_MIN, morton.COORD_MAX + 1, (5000, 3), generator=generator)
    edges = torch.tensor([morton.COORD_MIN, morton.COORD_MAX, -1, 0, 1])
    corners = torch.cartesian_prod(edges, edges, edges)
    coords = torch.cat([random, corners])
    codes = morton.encode(coords)
    assert codes.dtype == torch.int64
    assert bool((codes >= 0).all())
    assert torch.equal(morton.decode(codes), coords)
    assert int(morton.encode(torch.tensor([[morton.COORD_MAX] * 3]))) == (1 << 63) - 1


def test_matches_brute_force_interleave() -> None:
    grid = torch.cartesian_prod(*[torch.arange(-4, 4)] * 3)
    extremes = torch.tensor([[morton.COORD_MIN, 7, morton.COORD_MAX], [123456, -654321, 99]])
    coords = torch.cat([grid, extremes])
    expected = [interleave(*row) for row in coords.tolist()]
    assert morton.encode(coords).tolist() == expected


def test_aligned_2x2x2_blocks_are_consecutive() -> None:
    offsets = torch.cartesian_prod(*[torch.arange(2)] * 3)
    for base in ([0, 0, 0], [-2, 4, -8], [morton.COORD_MIN, morton.COORD_MAX - 1, 10]):
        codes = morton.encode(torch.tensor(base) + offsets).sort().values
        assert torch.equal(codes - codes[0], torch.arange(8))
        assert int(codes[0]) % 8 == 0


def test_out_of_range_and_bad_input() -> None:
    for value in (morton.COORD_MAX + 1, morton.COORD_MIN - 1):
        with pytest.raises(ValueError, match="must lie in"):
            morton.encode(torch.tensor([[0, value, 0]]))
    with pytest.raises(ValueError, match="integers"):
        morton.encode(torch.zeros(1, 3))
    with pytest.raises(ValueError, match="non-negative"):
        morton.decode(torch.tensor([-1]))
    assert morton.encode(torch.empty(0, 3, dtype=torch.int64)).shape == (0,)


def test_cell_coords_floors_negatives() -> None:
    points = torch.tensor([[0.05, -0.05, 0.25], [-0.1001, 0.0, 1.0]], dtype=torch.float64)
    assert morton.cell_coords(points, 0.1).tolist() == [[0, -1, 2], [-2, 0, 10]]
    with pytest.raises(ValueError, match="finite"):
        morton.cell_coords(torch.tensor([[float("nan"), 0.0, 0.0]]), 0.1)
    with pytest.raises(ValueError, match="positive"):
        morton.cell_coords(points, 0.0)
