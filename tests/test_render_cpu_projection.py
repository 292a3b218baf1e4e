"""The fused Numba projection against ``projection.project_gaussians``: outputs and gradients.

Outputs are compared with the torch projection run in float32 on the same inputs (the kernel
follows it operation by operation, so they agree to float32 rounding and cull identically);
gradients (the Gaussians' and the viewmat's) with torch autograd through it in float64, as
relative norm errors below 1e-4, overall and separately on the Gaussians that exercise each branch
(visible, clamped Jacobian, culled).
"""

from __future__ import annotations

import math

import ogmapping  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its thread pool)

# isort: split
import pytest
import torch

from ogmapping.render import Camera, SplatSet, cpu_backend, cpu_projection, rasterize
from ogmapping.render.projection import FOV_MARGIN, project_gaussians
from ogmapping.render.rules import ALPHA_MIN, COVARIANCE_BLUR

TOLERANCE = 1e-4
WIDTH, HEIGHT = 96, 72


def camera(seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """An off-centre principal point and a rotated, translated world-to-camera pose."""
    g = torch.Generator().manual_seed(seed)
    K = torch.tensor([[0.8 * WIDTH, 0.0, 0.45 * WIDTH], [0.0, 0.85 * WIDTH, 0.55 * HEIGHT], [0.0, 0.0, 1.0]])
    axis_angle = 0.3 * torch.randn(3, generator=g)
    viewmat = torch.eye(4)
    viewmat[:3, :3] = torch.linalg.matrix_exp(torch.linalg.cross(torch.eye(3), axis_angle.expand(3, 3)))
    viewmat[:3, 3] = 0.5 * torch.randn(3, generator=g)
    return viewmat, K


def scene(seed: int, n: int, viewmat: torch.Tensor, K: torch.Tensor) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """Gaussians placed by pixel and depth: in view, behind, far off-screen, beyond the Jacobian's
    clamp (some still reaching the image), tiny, huge, faint. Returns them and the kinds."""
    g = torch.Generator().manual_seed(seed)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    z = 0.5 + 3.5 * torch.rand(n, generator=g)
    u = (torch.rand(n, generator=g) * 1.2 - 0.1) * WIDTH
    v = (torch.rand(n, generator=g) * 1.2 - 0.1) * HEIGHT
    scales = torch.exp(torch.empty(n, 3).uniform_(math.log(0.005), math.log(0.08), generator=g))
    opacities = torch.empty(n).uniform_(0.05, 1.0, generator=g)
    kind = torch.randint(0, 10, (n,), generator=g)
    z[kind == 1] = torch.empty(int((kind == 1).sum())).uniform_(-2.0, 0.009, generator=g)
    u[kind == 2] += 20.0 * WIDTH
    beyond = (kind == 3) | (kind == 4)
    margin = (1.0 + FOV_MARGIN) * WIDTH
    sign = torch.randint(0, 2, (n,), generator=g) * 2 - 1
    u[beyond] = WIDTH / 2 + sign[beyond] * margin * torch.empty(int(beyond.sum())).uniform_(0.6, 0.9, generator=g)
    v[kind == 4] = HEIGHT / 2 + sign[kind == 4] * (1.0 + FOV_MARGIN) * HEIGHT * 0.8
    scales[beyond] *= 8.0
    scales[kind == 5] *= 0.01
    scales[kind == 6] = torch.empty(int((kind == 6).sum()), 3).uniform_(0.5, 2.0, generator=g)
    opacities[kind == 7] = 0.5 * ALPHA_MIN
    camera_points = torch.stack([(u - cx) / fx * z, (v - cy) / fy * z, z], dim=-1)
    means = (camera_points - viewmat[:3, 3]) @ viewmat[:3, :3]
    quats = torch.randn(n, 4, generator=g)
    return {"means": means, "quats": quats, "scales": scales, "opacities": opacities}, kind


def fused(params: dict[str, torch.Tensor], viewmat: torch.Tensor, K: torch.Tensor, blur: float = COVARIANCE_BLUR):
    arrays = [params[k].float().numpy() for k in ("means", "quats", "scales", "opacities")]
    return [*arrays, viewmat.float().numpy(), K.float().numpy(), WIDTH, HEIGHT, blur]


def relative_error(a: torch.Tensor, b: torch.Tensor) -> float:
    return float((a.double() - b.double()).norm() / b.double().norm().clamp_min(1e-30))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_forward_matches_torch_projection(seed: int) -> None:
    viewmat, K = camera(seed)
    params, kind = scene(seed, 4000, viewmat, K)
    means2d, conics, depths, radii = cpu_projection.project_forward(*fused(params, viewmat, K))
    ref = project_gaussians(*(params[k] for k in ("means", "quats", "scales", "opacities")), viewmat, K, WIDTH, HEIGHT)
    assert torch.equal(torch.from_numpy(radii), ref.radii)
    # Centres and depths are the same products and sums in the same order, so equal to the bit on
    # any CPU: a depth one ulp off would put Gaussians of equal depth in another order.
    assert torch.equal(torch.from_numpy(means2d), ref.means2d)
    assert torch.equal(torch.from_numpy(depths), ref.depths)
    torch.testing.assert_close(torch.from_numpy(conics), ref.conics, rtol=5e-5, atol=1e-8)  # inverse of a 2x2: cancels
    visible = ref.radii > 0
    # Every kind of Gaussian is represented, and the clamped ones partly reach the image.
    assert bool(visible[kind == 0].any()) and not bool(visible[(kind == 1) | (kind == 2) | (kind == 7)].any())
    assert 0 < int(visible[(kind == 3) | (kind == 4)].sum()) < int(((kind == 3) | (kind == 4)).sum())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gradients_match_autograd(seed: int) -> None:
    """Random upstream gradients on every Gaussian, culled ones included."""
    viewmat, K = camera(seed)
    params, kind = scene(seed, 4000, viewmat, K)
    n = kind.shape[0]
    g = torch.Generator().manual_seed(seed + 100)
    upstream = (torch.randn(n, 2, generator=g), torch.randn(n, 3, generator=g), torch.randn(n, generator=g))
    leaves = {k: params[k].double().clone().requires_grad_(True) for k in ("means", "quats", "scales")}
    ref = project_gaussians(
        leaves["means"], leaves["quats"], leaves["scales"], params["opacities"].double(), viewmat.double(),
        K.double(), WIDTH, HEIGHT,
    )
    outputs = (ref.means2d, ref.conics, ref.depths)
    sum((o * u.double()).sum() for o, u in zip(outputs, upstream, strict=True)).backward()
    *grads, grad_viewmat = cpu_projection.project_backward(*fused(params, viewmat, K),
                                                           *(u.numpy() for u in upstream), False)
    assert not grad_viewmat.any()

    visible = ref.radii > 0
    groups = {"all": torch.ones_like(visible), "visible": visible, "clamped": (kind == 3) | (kind == 4),
              "behind": kind == 1, "off-screen": kind == 2, "tiny": kind == 5, "huge": kind == 6}
    for name, grad in zip(("means", "quats", "scales"), grads, strict=True):
        grad = torch.from_numpy(grad)
        for group, mask in groups.items():
            error = relative_error(grad[mask], leaves[name].grad[mask])
            assert error < TOLERANCE, (name, group, error)


def test_clamped_jacobian_passes_no_gradient_through_the_clamp() -> None:
    """A Gaussian far beyond the clamp: its conic no longer depends on how far (zero x-gradient in
    the camera frame from the conic), while its centre still moves with it."""
    viewmat, K = torch.eye(4), torch.tensor([[50.0, 0.0, 32.0], [0.0, 50.0, 24.0], [0.0, 0.0, 1.0]])
    params = {"means": torch.tensor([[10.0, 0.1, 2.0]]), "quats": torch.tensor([[0.9, 0.1, 0.3, -0.2]]),
              "scales": torch.tensor([[0.3, 0.2, 0.1]]), "opacities": torch.tensor([0.8])}
    conic_only = (torch.zeros(1, 2), torch.ones(1, 3), torch.zeros(1))
    arrays = [params[k].numpy() for k in ("means", "quats", "scales", "opacities")]
    grad_means, _, _, _ = cpu_projection.project_backward(*arrays, viewmat.numpy(), K.numpy(), 64, 48, COVARIANCE_BLUR,
                                                          *(u.numpy() for u in conic_only), False)
    assert grad_means[0, 0] == 0.0 and grad_means[0, 2] != 0.0


def test_backend_opacity_gradient_comes_from_compositing_only() -> None:
    """The projection gives opacity no gradient; the backend's opacity gradient is compositing's,
    and float32 and float64 callers share one compiled signature of each projection kernel."""
    viewmat, K = camera(3)
    params, _ = scene(3, 500, viewmat, K)
    for dtype in (torch.float64, torch.float32):
        leaves = {k: v.to(dtype).clone().requires_grad_(True) for k, v in params.items()}
        colors = torch.rand(500, 3, dtype=dtype)
        splats = SplatSet(leaves["means"], leaves["quats"], leaves["scales"], leaves["opacities"], colors)
        out = cpu_backend.rasterize(splats, Camera(viewmat.to(dtype), K.to(dtype), WIDTH, HEIGHT))
        out.means2d.sum().backward()  # means2d alone: no path to the opacities
        assert leaves["opacities"].grad is None
        assert out.means2d.grad is not None and leaves["means"].grad.dtype == dtype
    for kernel in (cpu_projection.project_forward, cpu_projection.project_backward):
        assert len(kernel.signatures) == 1, kernel.signatures


@pytest.mark.parametrize(("seed", "blur"), [(0, COVARIANCE_BLUR), (1, COVARIANCE_BLUR), (2, COVARIANCE_BLUR),
                                          (3, COVARIANCE_BLUR / 4)])
def test_viewmat_gradient_matches_autograd(seed: int, blur: float) -> None:
    """The viewmat's gradient, from all Gaussians and from each kind alone (a clamped Jacobian, a
    centre behind the near plane), with the rest of the backward bit for bit the one without it; at
    the default blur and at a strided tracking render's."""
    viewmat, K = camera(seed)
    params, kind = scene(seed, 4000, viewmat, K)
    n = kind.shape[0]
    g = torch.Generator().manual_seed(seed + 200)
    upstream = (torch.randn(n, 2, generator=g), torch.randn(n, 3, generator=g), torch.randn(n, generator=g))
    groups = {"all": torch.ones(n, dtype=torch.bool), "visible": None, "clamped": (kind == 3) | (kind == 4),
              "behind": kind == 1, "off-screen": kind == 2, "tiny": kind == 5, "huge": kind == 6}
    for group, mask in groups.items():
        leaf = viewmat.double().clone().requires_grad_(True)
        ref = project_gaussians(*(params[k].double() for k in ("means", "quats", "scales", "opacities")), leaf,
                                K.double(), WIDTH, HEIGHT, blur)
        mask = ref.radii > 0 if mask is None else mask
        masked = [u * mask.view(-1, *(1,) * (u.dim() - 1)) for u in upstream]
        sum((o * u.double()).sum() for o, u in zip((ref.means2d, ref.conics, ref.depths), masked,
                                                   strict=True)).backward()
        arrays = [*fused(params, viewmat, K, blur), *(u.numpy() for u in masked)]
        *with_camera, grad_viewmat = cpu_projection.project_backward(*arrays, True)
        error = relative_error(torch.from_numpy(grad_viewmat), leaf.grad)
        assert error < TOLERANCE, (group, error)
        assert not grad_viewmat[3].any() and not leaf.grad[3].any()
        *without, _ = cpu_projection.project_backward(*arrays, False)
        for a, b in zip(with_camera, without, strict=True):
            assert a.tobytes() == b.tobytes(), group


def test_backend_routes_each_viewmat_its_gradient_only_when_asked(monkeypatch) -> None:
    """A viewmat that requires grad gets the reference's gradient; with fixed poses the projection's
    backward is never asked for camera terms and every other gradient is the same, bit for bit."""
    viewmat, K = camera(5)
    params, _ = scene(5, 500, viewmat, K)
    colors = torch.rand(500, 3, generator=torch.Generator().manual_seed(5))
    asked = []
    backward = cpu_projection.project_backward

    def recording(*args):
        asked.append(args[-1])
        return backward(*args)

    monkeypatch.setattr(cpu_projection, "project_backward", recording)
    results = {}
    for backend, dtype, posed in (("cpu", torch.float32, False), ("cpu", torch.float32, True),
                                  ("torch", torch.float64, True)):
        leaves = {k: v.to(dtype).clone().requires_grad_(True) for k, v in params.items()}
        pose = viewmat.to(dtype).clone().requires_grad_(posed)
        out = rasterize(SplatSet(*leaves.values(), colors.to(dtype)), Camera(pose, K.to(dtype), WIDTH, HEIGHT),
                        backend=backend)
        (out.color.sum() + 0.1 * out.depth.sum() + out.alpha.sum()).backward()
        results[backend, posed] = {**{k: v.grad for k, v in leaves.items()}, "viewmat": pose.grad}
    assert asked == [False, True]
    fixed, posed = results["cpu", False], results["cpu", True]
    assert fixed.pop("viewmat") is None and posed["viewmat"].dtype == torch.float32
    for name, grad in fixed.items():
        assert torch.equal(grad, posed[name]), name
    assert relative_error(posed["viewmat"], results["torch", True]["viewmat"]) < TOLERANCE


def test_intrinsics_gradient_is_refused() -> None:
    viewmat, K = camera(4)
    params, _ = scene(4, 10, viewmat, K)
    with pytest.raises(NotImplementedError, match="no gradient for K"):
        cpu_backend.rasterize(SplatSet(*params.values(), torch.rand(10, 3)),
                              Camera(viewmat, K.requires_grad_(True), WIDTH, HEIGHT))
