"""One encoding per step for the window's views: the same features and table gradient as one per view."""

import torch

from ogmapping.config import resolve
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.mapper import Mapper


def _mapped(preset: str) -> tuple[Mapper, list]:
    source = SyntheticSource(n_frames=3, width=64, height=48)
    mapper = Mapper(resolve(preset, overrides={"keyframes.first_iterations": 2, "keyframes.iterations": 1}))
    frames = [source[index] for index in range(3)]
    for frame in frames:
        mapper.process(frame)
    return mapper, frames


def _views(mapper: Mapper, frames: list) -> list[torch.Tensor]:
    return [mapper.model.rows_in_view(torch.as_tensor(frame.c2w, dtype=torch.float32), frame.color_intrinsics)
            for frame in frames]


def test_hash_features_encoded_once_match_per_view_encoding_in_value_and_table_gradient():
    mapper, frames = _mapped("dense")
    rows = _views(mapper, frames)
    assert all(len(view) for view in rows) and len(torch.unique(torch.cat(rows))) < sum(map(len, rows))
    weights = [torch.randn(len(view), mapper.model.encoding.output_dim, generator=torch.Generator().manual_seed(i))
               for i, view in enumerate(rows)]
    gradients = []
    for features in (mapper.model.window_features(rows), mapper.model.features):
        mapper.model.encoding.gradients.clear()
        outputs = [features(view) for view in rows]
        sum((output * weight).sum() for output, weight in zip(outputs, weights, strict=True)).backward()
        gradients.append((outputs, mapper.model.encoding.gradients.dense(mapper.model.encoding.table.shape)))
    (once, once_gradient), (per_view, per_view_gradient) = gradients
    for a, b in zip(once, per_view, strict=True):
        torch.testing.assert_close(a, b)
    assert per_view_gradient.abs().sum() > 0
    # Summed in another order (per anchor over the views, then per row), so equal to float32 rounding.
    scale = float(per_view_gradient.abs().max())
    torch.testing.assert_close(once_gradient, per_view_gradient, rtol=1e-4, atol=1e-5 * scale)
    mapper.model.encoding.gradients.clear()


def test_per_anchor_features_are_read_as_before():
    mapper, frames = _mapped("sparse")
    assert mapper.model.window_features(_views(mapper, frames)) == mapper.model.features
