"""The torch reference rasterizer against a naive per-pixel loop, plus gradcheck and edge cases."""

from __future__ import annotations

import math

import ogmapping  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its thread pool)

# isort: split
import pytest
import torch

from ogmapping.render.projection import project_gaussians
from ogmapping.render.rules import ALPHA_MAX, ALPHA_MIN, TRANSMITTANCE_MIN
from ogmapping.render.torch_backend import rasterize
from ogmapping.render.views import Camera, SplatSet

WIDTH, HEIGHT = 8, 6


def camera(dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """Identity pose and a pinhole with about a 60 degree horizontal field of view."""
    K = torch.tensor([[7.0, 0.0, 4.0], [0.0, 7.0, 3.0], [0.0, 0.0, 1.0]], dtype=dtype)
    return torch.eye(4, dtype=dtype), K


def random_scene(seed: int, n: int, dtype: torch.dtype = torch.float64) -> dict[str, torch.Tensor]:
    """Gaussians in front of the camera, some partly off-screen, sizes from sub-pixel to large."""
    g = torch.Generator().manual_seed(seed)
    z = 1.0 + 2.0 * torch.rand(n, generator=g, dtype=dtype)
    xy = (torch.rand(n, 2, generator=g, dtype=dtype) - 0.5) * 1.6 * z.unsqueeze(-1)
    return {
        "means": torch.cat([xy, z.unsqueeze(-1)], dim=-1),
        "quats": torch.randn(n, 4, generator=g, dtype=dtype),
        "scales": torch.exp(torch.empty(n, 3, dtype=dtype).uniform_(-3.5, -0.5, generator=g)),
        "opacities": torch.empty(n, dtype=dtype).uniform_(0.05, 1.0, generator=g),
        "colors": torch.rand(n, 3, generator=g, dtype=dtype),
    }


def naive_render(scene: dict[str, torch.Tensor], background: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Per-pixel loop over all unculled Gaussians in depth order, written straight from the rules."""
    viewmat, K = camera(scene["means"].dtype)
    proj = project_gaussians(
        scene["means"], scene["quats"], scene["scales"], scene["opacities"], viewmat, K, WIDTH, HEIGHT
    )
    order = [int(i) for i in torch.sort(proj.depths, stable=True).indices if proj.radii[i] > 0]
    color = torch.zeros(HEIGHT, WIDTH, 3, dtype=torch.float64)
    depth = torch.zeros(HEIGHT, WIDTH, dtype=torch.float64)
    alpha_out = torch.zeros(HEIGHT, WIDTH, dtype=torch.float64)
    for i in range(HEIGHT):
        for j in range(WIDTH):
            t, c, d = 1.0, torch.zeros(3, dtype=torch.float64), 0.0
            for k in order:
                dx = j + 0.5 - float(proj.means2d[k, 0])
                dy = i + 0.5 - float(proj.means2d[k, 1])
                a, b, cc = (float(v) for v in proj.conics[k])
                power = 0.5 * (a * dx * dx + 2.0 * b * dx * dy + cc * dy * dy)
                alpha = min(ALPHA_MAX, float(scene["opacities"][k]) * math.exp(-power))
                if alpha < ALPHA_MIN:
                    continue
                if t * (1.0 - alpha) < TRANSMITTANCE_MIN:
                    break
                c = c + alpha * t * scene["colors"][k].detach()
                d += alpha * t * float(proj.depths[k])
                t *= 1.0 - alpha
            color[i, j] = c + t * background
            alpha_out[i, j] = 1.0 - t
            depth[i, j] = d / (1.0 - t) if t < 1.0 else 0.0
    return color, depth, alpha_out


def render(scene: dict[str, torch.Tensor], background: torch.Tensor | None = None):
    viewmat, K = camera(scene["means"].dtype)
    splats = SplatSet(scene["means"], scene["quats"], scene["scales"], scene["opacities"], scene["colors"])
    return rasterize(splats, Camera(viewmat, K, WIDTH, HEIGHT), background)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_matches_naive_loop(seed: int) -> None:
    scene = random_scene(seed, 12)
    background = torch.tensor([0.2, 0.5, 0.9], dtype=torch.float64)
    out = render(scene, background)
    color, depth, alpha = naive_render(scene, background)
    torch.testing.assert_close(out.color, color, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(out.depth, depth, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(out.alpha, alpha, rtol=1e-10, atol=1e-12)


def test_stop_and_clamp_rules_are_exercised() -> None:
    """A stack of opaque Gaussians hits both ALPHA_MAX and the transmittance stop."""
    scene = random_scene(7, 12)
    scene["means"][:, :2] = 0.0
    scene["scales"][:] = 0.5
    scene["opacities"][:] = 1.0
    out = render(scene)
    color, depth, alpha = naive_render(scene, torch.zeros(3, dtype=torch.float64))
    assert float(alpha.max()) > 1.0 - 1e-3
    torch.testing.assert_close(out.color, color, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(out.depth, depth, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(out.alpha, alpha, rtol=1e-10, atol=1e-12)


def test_gaussian_that_stops_every_pixel() -> None:
    """A tiny opaque Gaussian ends compositing at every pixel it reaches; the faint layer behind it
    passes the transmittance test elsewhere, and would wrongly pass it there too if the stopping
    Gaussian were skipped (it contributes to no pixel itself)."""
    centre = 0.5 / 7.0  # a pixel centre, (4.5, 3.5), seen from the camera
    scene = {
        "means": torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.5], [2 * centre, 2 * centre, 2.0], [0.0, 0.0, 2.5]]),
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(4, 1),
        "scales": torch.tensor([[50.0] * 3, [50.0] * 3, [1e-3] * 3, [50.0] * 3]),
        # T = 1 - ALPHA_MAX after the first (its alpha is clamped), about 1.02e-4 after the second.
        "opacities": torch.tensor([1.0, 1.0 - 1.02e-4 / (1.0 - ALPHA_MAX), 0.99, 0.005]),
        "colors": torch.eye(4)[:, :3] + 0.1,
    }
    scene = {k: v.double() for k, v in scene.items()}
    out = render(scene)
    color, depth, alpha = naive_render(scene, torch.zeros(3, dtype=torch.float64))
    torch.testing.assert_close(out.color, color, rtol=1e-10, atol=1e-14)
    torch.testing.assert_close(out.depth, depth, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(out.alpha, alpha, rtol=1e-10, atol=1e-14)


def test_projection_matches_matrix_form() -> None:
    """Means, depths and 2D covariances against the textbook EWA formulas with explicit matrices."""
    scene = random_scene(5, 12)
    angle = torch.tensor(0.3, dtype=torch.float64)
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = torch.tensor(
        [[torch.cos(angle), 0.0, torch.sin(angle)], [0.0, 1.0, 0.0], [-torch.sin(angle), 0.0, torch.cos(angle)]]
    )
    viewmat[:3, 3] = torch.tensor([0.1, -0.2, 0.3])
    _, K = camera()
    proj = project_gaussians(
        scene["means"], scene["quats"], scene["scales"], scene["opacities"], viewmat, K, WIDTH, HEIGHT
    )
    p_cam = scene["means"] @ viewmat[:3, :3].T + viewmat[:3, 3]
    assert bool((p_cam[:, 2] > 0.5).all())
    x, y, z = p_cam.unbind(-1)
    torch.testing.assert_close(proj.depths, z)
    torch.testing.assert_close(proj.means2d[:, 0], K[0, 0] * x / z + K[0, 2])
    torch.testing.assert_close(proj.means2d[:, 1], K[1, 1] * y / z + K[1, 2])

    q = torch.nn.functional.normalize(scene["quats"], dim=-1)
    w, qx, qy, qz = q.unbind(-1)
    rot = torch.stack([
        1 - 2 * (qy**2 + qz**2), 2 * (qx * qy - w * qz), 2 * (qx * qz + w * qy),
        2 * (qx * qy + w * qz), 1 - 2 * (qx**2 + qz**2), 2 * (qy * qz - w * qx),
        2 * (qx * qz - w * qy), 2 * (qy * qz + w * qx), 1 - 2 * (qx**2 + qy**2),
    ], dim=-1).reshape(-1, 3, 3)
    cov3d = rot @ torch.diag_embed(scene["scales"] ** 2) @ rot.transpose(1, 2)
    # The principal point is the image centre, so the Jacobian limits are 3DGS's symmetric 1.3x FOV.
    lim_x = 1.3 * 0.5 * WIDTH / K[0, 0]
    lim_y = 1.3 * 0.5 * HEIGHT / K[1, 1]
    tx = (x / z).clamp(-lim_x, lim_x)
    ty = (y / z).clamp(-lim_y, lim_y)
    jac = torch.zeros(len(z), 2, 3, dtype=torch.float64)
    jac[:, 0, 0] = K[0, 0] / z
    jac[:, 0, 2] = -K[0, 0] * tx / z
    jac[:, 1, 1] = K[1, 1] / z
    jac[:, 1, 2] = -K[1, 1] * ty / z
    w_rot = viewmat[:3, :3]
    cov2d = jac @ w_rot @ cov3d @ w_rot.T @ jac.transpose(1, 2) + 0.3 * torch.eye(2, dtype=torch.float64)
    a, b, c = proj.conics.unbind(-1)
    inverse = torch.stack([torch.stack([a, b], -1), torch.stack([b, c], -1)], -2)
    torch.testing.assert_close(inverse @ cov2d, torch.eye(2, dtype=torch.float64).expand(len(z), 2, 2))


def smooth_scene() -> dict[str, torch.Tensor]:
    """Three large, half-transparent Gaussians near the image centre.

    Every Gaussian keeps alpha well inside (ALPHA_MIN, ALPHA_MAX) at every pixel and the
    transmittance never approaches TRANSMITTANCE_MIN, so the render is smooth in all parameters
    and finite differences are valid (``test_gradcheck`` asserts these margins).
    """
    g = torch.Generator().manual_seed(11)
    n = 3
    return {
        "means": torch.tensor([[0.05, -0.02, 2.0], [-0.1, 0.08, 2.5], [0.12, 0.1, 3.0]], dtype=torch.float64),
        "quats": torch.randn(n, 4, generator=g, dtype=torch.float64),
        "scales": torch.tensor([[0.6, 0.9, 0.5], [1.0, 0.7, 0.8], [0.8, 1.1, 0.9]], dtype=torch.float64),
        "opacities": torch.tensor([0.5, 0.4, 0.6], dtype=torch.float64),
        "colors": torch.rand(n, 3, generator=g, dtype=torch.float64),
    }


def assert_smooth(scene: dict[str, torch.Tensor], viewmat: torch.Tensor, K: torch.Tensor) -> None:
    """Every Gaussian visible, and alpha and transmittance at every pixel clear of the thresholds."""
    proj = project_gaussians(
        scene["means"], scene["quats"], scene["scales"], scene["opacities"], viewmat, K, WIDTH, HEIGHT
    )
    assert bool((proj.radii > 0).all())
    rows, cols = torch.meshgrid(torch.arange(HEIGHT) + 0.5, torch.arange(WIDTH) + 0.5, indexing="ij")
    d = torch.stack([cols, rows], dim=-1).reshape(-1, 1, 2).double() - proj.means2d
    a, b, c = proj.conics.unbind(-1)
    power = 0.5 * (a * d[..., 0] ** 2 + c * d[..., 1] ** 2) + b * d[..., 0] * d[..., 1]
    raw_alpha = scene["opacities"] * torch.exp(-power)
    assert float(raw_alpha.min()) > 2 * ALPHA_MIN and float(raw_alpha.max()) < 0.9 * ALPHA_MAX
    assert float(torch.prod(1.0 - raw_alpha, dim=1).min()) > 100 * TRANSMITTANCE_MIN


def test_gradcheck() -> None:
    scene = smooth_scene()
    viewmat, K = camera()
    assert_smooth(scene, viewmat, K)

    background = torch.tensor([0.3, 0.1, 0.7], dtype=torch.float64)
    names = ("means", "quats", "scales", "opacities", "colors")
    inputs = tuple(scene[name].clone().requires_grad_(True) for name in names)

    def fn(*params: torch.Tensor) -> tuple[torch.Tensor, ...]:
        out = rasterize(SplatSet(*params), Camera(viewmat, K, WIDTH, HEIGHT), background)
        return out.color, out.depth, out.alpha

    assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-6, rtol=1e-4)


def test_gradcheck_viewmat() -> None:
    """The viewmat's gradient (pose refinement) against finite differences, at a rotated and
    translated pose; its last row, which the projection never reads, gets none."""
    scene = smooth_scene()
    _, K = camera()
    wx, wy, wz = 0.03, -0.02, 0.05
    viewmat = torch.eye(4, dtype=torch.float64)
    viewmat[:3, :3] = torch.linalg.matrix_exp(
        torch.tensor([[0.0, -wz, wy], [wz, 0.0, -wx], [-wy, wx, 0.0]], dtype=torch.float64))
    viewmat[:3, 3] = torch.tensor([0.02, -0.03, 0.05], dtype=torch.float64)
    assert_smooth(scene, viewmat, K)
    background = torch.tensor([0.3, 0.1, 0.7], dtype=torch.float64)
    params = tuple(scene[name] for name in ("means", "quats", "scales", "opacities", "colors"))

    def fn(pose: torch.Tensor) -> tuple[torch.Tensor, ...]:
        out = rasterize(SplatSet(*params), Camera(pose, K, WIDTH, HEIGHT), background)
        return out.color, out.depth, out.alpha

    leaf = viewmat.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(fn, (leaf,), eps=1e-6, atol=1e-6, rtol=1e-4)
    out = rasterize(SplatSet(*params), Camera(leaf, K, WIDTH, HEIGHT), background)
    (out.color.sum() + out.depth.sum() + out.alpha.sum()).backward()
    assert bool(leaf.grad[:3].abs().gt(0).all()) and not bool(leaf.grad[3].any())


def test_means2d_gradient_is_retained() -> None:
    scene = {k: v.clone().requires_grad_(True) for k, v in smooth_scene().items()}
    out = render(scene)
    (out.color.sum() + out.depth.sum()).backward()
    assert out.means2d.grad is not None and out.means2d.grad.shape == (3, 2)
    assert float(out.means2d.grad.abs().sum()) > 0
    assert bool(out.visible.all())


def test_empty_scene() -> None:
    empty = {k: v[:0].clone().requires_grad_(True) for k, v in random_scene(0, 4).items()}
    background = torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64)
    out = render(empty, background)
    torch.testing.assert_close(out.color, background.expand(HEIGHT, WIDTH, 3))
    assert bool((out.depth == 0).all()) and bool((out.alpha == 0).all())
    assert out.means2d.shape == (0, 2) and out.visible.shape == (0,)


def test_all_culled() -> None:
    """Behind the camera, off to the side, and too transparent: nothing reaches a pixel."""
    scene = random_scene(3, 6)
    scene["means"][0:2, 2] = -1.0
    scene["means"][2:4, 0] = 50.0
    scene["opacities"][4:6] = 0.5 * ALPHA_MIN
    scene = {k: v.requires_grad_(True) for k, v in scene.items()}
    background = torch.tensor([0.4, 0.4, 0.4], dtype=torch.float64)
    out = render(scene, background)
    assert not bool(out.visible.any())
    torch.testing.assert_close(out.color, background.expand(HEIGHT, WIDTH, 3))
    assert bool((out.depth == 0).all()) and bool((out.alpha == 0).all())
    assert out.means2d.shape == (6, 2)
    out.color.sum().backward()
    assert float(scene["means"].grad.abs().sum()) == 0.0
