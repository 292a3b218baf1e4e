"""The compiled cpu rasterizer against the torch reference: images and every gradient.

Metric: relative norm error ``||cpu - ref|| / ||ref||`` per output or gradient, against the
reference run in float64 on the same inputs, with tolerance 1e-4. The cpu kernels composite in
float32 (about 6e-8 relative rounding per operation, a few hundred operations deep per pixel), so
honest agreement sits near 1e-6; an elementwise bound would be dominated by the few pixels where
float32 rounding flips a threshold decision (alpha right at ALPHA_MIN, transmittance right at
TRANSMITTANCE_MIN), which change a pixel by at most about ALPHA_MIN and are noise in the norm.
"""

from __future__ import annotations

import math

import ogmapping  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its thread pool)

# isort: split
import numpy as np
import pytest
import torch

from ogmapping.render import Camera, SplatSet, cpu_backend, cpu_kernels, torch_backend
from ogmapping.render.rules import ALPHA_MIN, COVARIANCE_BLUR

TOLERANCE = 1e-4
PARAMS = ("means", "quats", "scales", "opacities", "colors")


def intrinsics(width: int, height: int) -> torch.Tensor:
    focal = 0.8 * width
    return torch.tensor([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])


def mixed_scene(seed: int, n: int, width: int, height: int) -> dict[str, torch.Tensor]:
    """Gaussians in the frustum plus ones behind the camera, off-screen, tiny, huge, opaque, faint."""
    g = torch.Generator().manual_seed(seed)
    focal = 0.8 * width
    z = 1.0 + 3.0 * torch.rand(n, generator=g)
    u = (torch.rand(n, generator=g) * 1.2 - 0.1) * width
    v = (torch.rand(n, generator=g) * 1.2 - 0.1) * height
    means = torch.stack([(u - width / 2) / focal * z, (v - height / 2) / focal * z, z], dim=-1)
    scales = torch.exp(torch.empty(n, 3).uniform_(math.log(0.005), math.log(0.05), generator=g))
    opacities = torch.empty(n).uniform_(0.1, 0.9, generator=g)
    kind = torch.randint(0, 100, (n,), generator=g)
    means[kind < 5, 2] = torch.empty(int((kind < 5).sum())).uniform_(-2.0, 0.005, generator=g)
    means[(kind >= 5) & (kind < 10), 0] += 5.0 * means[(kind >= 5) & (kind < 10), 2]
    scales[(kind >= 10) & (kind < 20)] *= 0.02
    scales[kind == 20] = torch.empty(int((kind == 20).sum()), 3).uniform_(0.5, 2.0, generator=g)
    opacities[(kind >= 21) & (kind < 25)] = 1.0
    opacities[kind == 25] = 0.5 * ALPHA_MIN
    return {
        "means": means,
        "quats": torch.randn(n, 4, generator=g),
        "scales": scales,
        "opacities": opacities,
        "colors": torch.rand(n, 3, generator=g),
    }


def render_and_grad(backend, scene, width, height, dtype, background=None, blur=COVARIANCE_BLUR):
    """Render, backprop a random weighting of colour, depth and alpha; return outputs and grads."""
    leaves = {k: v.to(dtype).clone().requires_grad_(True) for k, v in scene.items()}
    bg = None if background is None else background.to(dtype)
    camera = Camera(torch.eye(4, dtype=dtype), intrinsics(width, height).to(dtype), width, height, blur)
    out = backend.rasterize(SplatSet(*(leaves[k] for k in PARAMS)), camera, bg)
    g = torch.Generator().manual_seed(123)
    loss = (
        (out.color * torch.rand(out.color.shape, generator=g).to(dtype)).sum()
        + (out.depth * torch.rand(out.depth.shape, generator=g).to(dtype)).sum()
        + (out.alpha * torch.rand(out.alpha.shape, generator=g).to(dtype)).sum()
    )
    loss.backward()
    results = {"color": out.color, "depth": out.depth, "alpha": out.alpha, "means2d.grad": out.means2d.grad}
    results.update({f"{k}.grad": leaves[k].grad for k in PARAMS})
    return out, {k: v.detach() for k, v in results.items()}


def relative_error(a: torch.Tensor, b: torch.Tensor) -> float:
    denom = b.double().norm()
    diff = (a.double() - b.double()).norm()
    return float(diff) if float(denom) == 0.0 else float(diff / denom)


def assert_parity(scene, width, height, background=None, blur=COVARIANCE_BLUR) -> dict[str, float]:
    out_cpu, cpu = render_and_grad(cpu_backend, scene, width, height, torch.float32, background, blur)
    out_ref, ref = render_and_grad(torch_backend, scene, width, height, torch.float64, background, blur)
    assert torch.equal(out_cpu.visible, out_ref.visible)
    errors = {k: relative_error(cpu[k], ref[k]) for k in ref}
    assert all(math.isfinite(e) for e in errors.values()), errors
    assert max(errors.values()) < TOLERANCE, errors
    return errors


@pytest.mark.parametrize(
    ("seed", "n", "width", "height"),
    [(0, 200, 64, 48), (1, 800, 64, 48), (2, 2000, 64, 48), (3, 1500, 160, 120), (10, 600, 53, 37)],
)
def test_parity_mixed_scenes(seed: int, n: int, width: int, height: int) -> None:
    """Several seeds and sizes, including partial edge tiles (53x37)."""
    scene = mixed_scene(seed, n, width, height)
    assert_parity(scene, width, height, torch.tensor([0.3, 0.6, 0.1]))


@pytest.mark.parametrize("blur", [0.075, 1.2])
def test_parity_with_another_blur(blur: float) -> None:
    """A camera's blur other than the default (a strided tracking render's) in both backends."""
    scene = mixed_scene(11, 800, 64, 48)
    assert_parity(scene, 64, 48, torch.tensor([0.2, 0.5, 0.4]), blur)


def test_parity_opaque_stack() -> None:
    """Opaque Gaussians piled up on the optical axis: ALPHA_MAX clamping and the early stop."""
    scene = mixed_scene(4, 60, 64, 48)
    scene["means"][:, :2] *= 0.1
    scene["means"][:, 2] = torch.linspace(1.0, 3.0, 60)
    scene["scales"][:] = torch.tensor([0.2, 0.12, 0.16])
    scene["opacities"][:] = torch.linspace(0.7, 1.0, 60)
    out, _ = render_and_grad(cpu_backend, scene, 64, 48, torch.float32)
    assert float(out.alpha.detach().max()) > 1.0 - 1e-3
    assert_parity(scene, 64, 48)


def test_parity_equal_depths() -> None:
    """Overlapping Gaussians at exactly the same depth composite in index order in both backends."""
    scene = mixed_scene(9, 50, 64, 48)
    scene["means"][:, 2] = 2.0
    scene["means"][:, :2] *= 0.2
    assert_parity(scene, 64, 48, torch.tensor([0.1, 0.1, 0.1]))


def test_empty_scene() -> None:
    scene = {k: v[:0] for k, v in mixed_scene(5, 4, 64, 48).items()}
    background = torch.tensor([0.2, 0.4, 0.6])
    out, grads = render_and_grad(cpu_backend, scene, 64, 48, torch.float32, background)
    torch.testing.assert_close(out.color, background.expand(48, 64, 3))
    assert bool((out.alpha == 0).all()) and bool((out.depth == 0).all())
    assert out.means2d.shape == (0, 2) and grads["means.grad"].shape == (0, 3)


def test_all_culled() -> None:
    scene = mixed_scene(6, 30, 64, 48)
    scene["means"][:10, 2] = -1.0
    scene["means"][10:20, 0] = 100.0
    scene["opacities"][20:] = 0.5 * ALPHA_MIN
    background = torch.tensor([0.5, 0.5, 0.5])
    out, grads = render_and_grad(cpu_backend, scene, 64, 48, torch.float32, background)
    assert not bool(out.visible.any())
    torch.testing.assert_close(out.color, background.expand(48, 64, 3))
    assert all(float(grads[f"{k}.grad"].abs().sum()) == 0.0 for k in PARAMS)


def test_float64_inputs_keep_dtype_and_one_signature() -> None:
    """float64 callers get float64 outputs from the same compiled float32 kernels."""
    scene = mixed_scene(7, 300, 64, 48)
    out, grads = render_and_grad(cpu_backend, scene, 64, 48, torch.float64)
    assert out.color.dtype == torch.float64 and grads["means.grad"].dtype == torch.float64
    render_and_grad(cpu_backend, scene, 64, 48, torch.float32)
    kernels = (cpu_kernels.bin_tiles, cpu_kernels.render_forward, cpu_kernels.render_backward, cpu_kernels.reduce_pairs)
    for kernel in kernels:
        assert len(kernel.signatures) == 1, kernel.signatures


def test_background_gradient() -> None:
    scene = mixed_scene(8, 100, 64, 48)
    for backend in (cpu_backend, torch_backend):
        background = torch.tensor([0.2, 0.3, 0.4], dtype=torch.float64 if backend is torch_backend else None)
        background.requires_grad_(True)
        leaves = [scene[k].to(background.dtype) for k in PARAMS]
        camera = Camera(torch.eye(4, dtype=background.dtype), intrinsics(64, 48).to(background.dtype), 64, 48)
        out = backend.rasterize(SplatSet(*leaves), camera, background)
        out.color.sum().backward()
        expected = (1.0 - out.alpha.detach()).sum().double()
        torch.testing.assert_close(background.grad.double(), expected.expand(3), rtol=1e-5, atol=1e-3)


def test_depth_order_is_a_stable_sort() -> None:
    """Ties (float32 depths tie often), negative depths and -0.0 order as a stable argsort does."""
    rng = np.random.default_rng(3)
    depths = rng.choice(np.array([-2.5, -0.0, 0.0, 0.25, 1.0, 1.0000001, 3.0], np.float32), 5000)
    depths[::3] = rng.random(len(depths[::3]), dtype=np.float32) * 4.0
    visible = np.flatnonzero(rng.random(depths.size) > 0.3)
    expected = visible[np.argsort(depths[visible], kind="stable")]
    assert np.array_equal(cpu_backend._depth_order(depths, visible), expected)
