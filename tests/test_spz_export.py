"""``ogmap export --format spz``: Niantic's SPZ read back, by gsply and by the format's documented layout
(gzip; a 16-byte header, then positions, alphas, colours, scales, rotations), within its quantisation and
in its right-up-back axes."""

from __future__ import annotations

import gzip
import struct
import sys

import numpy as np
import pytest
import torch

from ogmapping.cli.commands import main as ogmap
from ogmapping.model.gaussians import GaussianSet
from ogmapping.persist.export import SH_C0
from ogmapping.persist.spz import RDF_TO_RUB, write_spz

gsply = pytest.importorskip("gsply", reason="the spz extra (gsply) is not installed")

NGSP = 0x5053474E  # "NGSP", little-endian
COUNT = 500


def gaussians(seed: int = 0) -> GaussianSet:
    generator = torch.Generator().manual_seed(seed)

    def uniform(*shape: int, low: float = 0.0, high: float = 1.0) -> torch.Tensor:
        return low + (high - low) * torch.rand(*shape, generator=generator)

    empty = torch.zeros(COUNT, dtype=torch.long)
    return GaussianSet(means=uniform(COUNT, 3, low=-3, high=3), quats=torch.randn(COUNT, 4, generator=generator),
                       scales=uniform(COUNT, 3, low=0.002, high=0.2), opacities=uniform(COUNT, low=0.02, high=0.98),
                       colors=uniform(COUNT, 3, low=0.05, high=0.95), rows=empty, slots=empty, anchor_rows=empty,
                       anchor_opacity=torch.zeros(COUNT))


def rotation(quats: np.ndarray) -> np.ndarray:
    w, x, y, z = np.moveaxis(quats / np.linalg.norm(quats, axis=1, keepdims=True), 1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def test_spz_reads_back_within_its_quantisation_in_rub_axes(tmp_path) -> None:
    source = gaussians()
    path = tmp_path / "map.spz"
    assert write_spz(source, path) == COUNT
    read = gsply.read_spz(path)
    means = source.means.numpy() * RDF_TO_RUB
    np.testing.assert_allclose(read.means, means, atol=0.5 / 4096 + 1e-6)  # 12 fractional bits
    alpha = 1 / (1 + np.exp(-np.asarray(read.opacities, dtype=np.float64)))
    np.testing.assert_allclose(alpha, source.opacities.numpy(), atol=0.5 / 255 + 1e-4)
    colors = np.asarray(read.sh0) * SH_C0 + 0.5
    np.testing.assert_allclose(colors, source.colors.numpy(), atol=0.5 / (0.15 * 255) * SH_C0 + 1e-4)
    np.testing.assert_allclose(read.scales, np.log(source.scales.numpy()), atol=0.5 / 16 + 1e-4)
    # Each Gaussian turned by the same half turn about x as the positions: R' = F R F.
    flip = np.diag(RDF_TO_RUB)
    np.testing.assert_allclose(rotation(np.asarray(read.quats)), flip @ rotation(source.quats.numpy()) @ flip,
                               atol=0.01)


def test_spz_has_the_documented_layout(tmp_path) -> None:
    source = gaussians(1)
    path = tmp_path / "map.spz"
    write_spz(source, path)
    payload = gzip.decompress(path.read_bytes())
    magic, version, count, sh_degree, fractional_bits, _flags, _reserved = struct.unpack_from("<IIIBBBB", payload)
    assert (magic, version, count, sh_degree, fractional_bits) == (NGSP, 3, COUNT, 0, 12)
    assert len(payload) == 16 + COUNT * (9 + 1 + 3 + 3 + 4)  # positions, alpha, colour, scale, smallest-three
    raw = np.frombuffer(payload, np.uint8, 9 * COUNT, 16).reshape(COUNT, 3, 3).astype(np.int32)
    fixed = raw[..., 0] | raw[..., 1] << 8 | raw[..., 2] << 16
    fixed = np.where(fixed >= 1 << 23, fixed - (1 << 24), fixed)
    np.testing.assert_allclose(fixed / 4096, source.means.numpy() * RDF_TO_RUB, atol=0.5 / 4096 + 1e-6)
    alphas = np.frombuffer(payload, np.uint8, COUNT, 16 + 9 * COUNT)
    np.testing.assert_allclose(alphas / 255, source.opacities.numpy(), atol=0.5 / 255 + 1e-4)
    colors = np.frombuffer(payload, np.uint8, 3 * COUNT, 16 + 10 * COUNT).reshape(COUNT, 3)
    np.testing.assert_allclose((colors - 127.5) / (0.15 * 255) * SH_C0 + 0.5, source.colors.numpy(),
                               atol=0.5 / (0.15 * 255) * SH_C0 + 1e-4)


def test_ogmap_export_writes_spz_by_flag_or_suffix(tmp_path, tiny_snapshot, capsys) -> None:
    snapshot = tiny_snapshot
    for out, flags in ((tmp_path / "a.spz", []), (tmp_path / "b.bin", ["--format", "spz"]),
                       (tmp_path / "c.ply", [])):
        assert ogmap(["export", "--snapshot", str(snapshot), "--out", str(out), *flags]) == 0
    said = capsys.readouterr().out
    assert "a.spz (spz)" in said and "b.bin (spz)" in said and "c.ply (ply)" in said
    ply_count = int(said.split("wrote ")[3].split()[0])
    assert len(gsply.read_spz(tmp_path / "a.spz").means) == ply_count
    assert (tmp_path / "a.spz").read_bytes() == (tmp_path / "b.bin").read_bytes()
    assert (tmp_path / "a.spz").stat().st_size < (tmp_path / "c.ply").stat().st_size / 4


def test_without_gsply_the_export_says_which_extra(tmp_path, monkeypatch) -> None:
    monkeypatch.setitem(sys.modules, "gsply", None)
    with pytest.raises(ValueError, match=r"--format spz needs the gsply package: pip install 'ogmapping\[spz\]'"):
        write_spz(gaussians(), tmp_path / "map.spz")
