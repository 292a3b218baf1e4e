"""Snapshot round trip renders the same images; corrupt snapshots are refused; PLY export."""

import numpy as np
import pytest

from ogmapping.config import build
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.mapper import Mapper
from ogmapping.snapshot import read_metadata


@pytest.fixture(scope="module", params=["dense", "sparse"])
def mapped(request):
    source = SyntheticSource(n_frames=4, width=64, height=48)
    config = build(request.param, {"keyframes.iterations": 4, "keyframes.first_iterations": 12,
                                   "refine.interval": 4, "refine.min_observations": 1})
    mapper = Mapper(config)
    for position in range(len(source)):
        mapper.process(source[position])
    return mapper, source


def test_round_trip_renders_within_float16_tolerance(mapped):
    mapper, source = mapped
    data = mapper.snapshot()
    restored = Mapper.restore(data)
    assert len(restored.anchors) == len(mapper.anchors)
    assert restored.anchors.levels.tolist() == mapper.anchors.levels.tolist()
    for position in (0, 3):
        frame = source[position]
        before = mapper.render(frame.c2w, frame.color_intrinsics)
        after = restored.render(frame.c2w, frame.color_intrinsics)
        assert np.abs(before.color - after.color).max() < 2e-2
        assert np.abs(before.color - after.color).mean() < 2e-3
        valid = (before.alpha > 0.5) & (after.alpha > 0.5)
        assert np.abs(before.depth - after.depth)[valid].mean() < 2e-3


def test_restored_map_keeps_mapping(mapped):
    mapper, source = mapped
    restored = Mapper.restore(mapper.snapshot())
    result = restored.process(source[1])
    assert result.keyframe and result.iterations > 0
    assert restored.stats().frames == mapper.frames + 1


def test_snapshot_metadata_and_corruption(mapped):
    mapper, _ = mapped
    data = mapper.snapshot()
    metadata = read_metadata(data)
    assert metadata["format"] == "ogmapping-snapshot" and "config" in metadata
    with pytest.raises(ValueError, match="truncated"):
        Mapper.restore(data[:4])
    with pytest.raises(ValueError):
        Mapper.restore(data[: len(data) // 2])
    with pytest.raises(ValueError, match=r"not an ogmapping snapshot|not valid JSON|out of range"):
        Mapper.restore(b"\x10\x00\x00\x00\x00\x00\x00\x00" + b"{" * 16 + b"payload")


def test_ply_export_has_the_3dgs_layout(mapped, tmp_path):
    from ogmapping.export import export_ply

    mapper, _ = mapped
    path = tmp_path / "map.ply"
    count = export_ply(mapper, path)
    raw = path.read_bytes()
    header, _, body = raw.partition(b"end_header\n")
    assert b"element vertex %d" % count in header
    for name in (b"x", b"f_dc_0", b"opacity", b"scale_2", b"rot_3"):
        assert b"property float " + name + b"\n" in header
    assert len(body) == count * 17 * 4
