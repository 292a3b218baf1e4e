"""A camera on every s-th pixel with the blur divided by s^2 renders the full image's pixels, in every CPU
backend: what pose tracking relies on to score the full-size loss on a quarter of the pixels."""

from __future__ import annotations

import math

import ogmapping  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its thread pool)

# isort: split
import pytest
import torch

from ogmapping.frames.camera import Intrinsics
from ogmapping.render import Camera, SplatSet, rasterize
from ogmapping.render.rules import COVARIANCE_BLUR

FULL = Intrinsics(fx=52.0, fy=50.0, cx=40.3, cy=29.6, width=80, height=60)


def scene_in_view(seed: int, n: int) -> dict[str, torch.Tensor]:
    """Gaussians whose centres project inside the image, from sub-pixel to several pixels wide."""
    g = torch.Generator().manual_seed(seed)
    z = 1.0 + 2.0 * torch.rand(n, generator=g, dtype=torch.float64)
    u = torch.rand(n, generator=g, dtype=torch.float64) * FULL.width
    v = torch.rand(n, generator=g, dtype=torch.float64) * FULL.height
    means = torch.stack([(u - FULL.cx) / FULL.fx * z, (v - FULL.cy) / FULL.fy * z, z], dim=-1)
    return {
        "means": means,
        "quats": torch.randn(n, 4, generator=g, dtype=torch.float64),
        "scales": torch.exp(torch.empty(n, 3, dtype=torch.float64).uniform_(math.log(0.002), math.log(0.06),
                                                                           generator=g)),
        "opacities": torch.empty(n, dtype=torch.float64).uniform_(0.1, 0.95, generator=g),
        "colors": torch.rand(n, 3, generator=g, dtype=torch.float64),
    }


def render(scene, intrinsics: Intrinsics, blur: float, backend: str, dtype: torch.dtype):
    K = torch.tensor(intrinsics.matrix(), dtype=dtype)
    splats = SplatSet(*(scene[k].to(dtype) for k in ("means", "quats", "scales", "opacities", "colors")))
    return rasterize(splats, Camera(torch.eye(4, dtype=dtype), K, intrinsics.width, intrinsics.height, blur),
                     backend=backend)


@pytest.mark.parametrize(("backend", "dtype", "tolerance"), [("torch", torch.float64, 1e-9),
                                                              ("cpu", torch.float32, 2e-4)])
@pytest.mark.parametrize(("stride", "start"), [(2, 0), (2, 1), (3, 1)])
def test_a_strided_camera_renders_the_full_images_pixels(backend, dtype, tolerance, stride, start):
    scene = scene_in_view(stride + start, 600)
    full = render(scene, FULL, COVARIANCE_BLUR, backend, dtype)
    strided = render(scene, FULL.strided(stride, start), COVARIANCE_BLUR / stride**2, backend, dtype)
    for name in ("color", "depth", "alpha"):
        expected = getattr(full, name)[start::stride, start::stride]
        assert float(expected.std()) > 0.05, name  # a scene that fills the image, edges and all
        torch.testing.assert_close(getattr(strided, name), expected, rtol=0, atol=tolerance)
    plain = render(scene, FULL.strided(stride, start), COVARIANCE_BLUR, backend, dtype)
    assert float((plain.color - strided.color).abs().max()) > 0.05  # the blur is what makes them agree
