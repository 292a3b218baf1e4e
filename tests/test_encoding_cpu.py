"""The compiled hash-grid encoding against the torch one: rows, features and the table's gradient."""

import torch

from ogmapping.config import ModelConfig
from ogmapping.model.encoding import HashGridEncoding


def encoding_and_points(count: int = 300) -> tuple[HashGridEncoding, torch.Tensor]:
    generator = torch.Generator().manual_seed(0)
    encoding = HashGridEncoding(ModelConfig(hash_log2_size=12), generator)
    with torch.no_grad():
        encoding.table.normal_(generator=generator)
    points = (torch.rand(count, 3, generator=generator) - 0.5) * 8.0  # negative coordinates too
    return encoding, points


def test_features_match_the_torch_encoding():
    encoding, points = encoding_and_points()
    compiled = encoding(points, compiled=True)
    reference = encoding(points, compiled=False)
    torch.testing.assert_close(compiled, reference, rtol=1e-5, atol=1e-6)


def test_table_gradient_matches_the_torch_encoding():
    encoding, points = encoding_and_points()
    weights = torch.randn(points.shape[0], encoding.output_dim, generator=torch.Generator().manual_seed(1))
    gradients = []
    for compiled in (True, False):
        encoding.gradients.clear()
        (encoding(points, compiled=compiled) * weights).sum().backward()
        gradients.append(encoding.gradients.dense(encoding.table.shape))
    assert gradients[0].abs().sum() > 0
    torch.testing.assert_close(gradients[0], gradients[1], rtol=1e-5, atol=1e-6)
