"""The gsplat CUDA backend against the pure-torch reference: renders and gradients.

Tolerances are gsplat's own for its CUDA kernels against its torch implementation (gsplat v1.5.3):
- renders, alphas: rtol = atol = 1e-4, tests/test_rasterization.py::test_rasterization;
- projected means: 1e-4; gradients of means (1e-2, 6e-2), quats (2e-1, 2e-2), scales (5e-1, 2e-1)
  as (rtol, atol): tests/test_basic.py::test_projection;
- gradients of means2d (5e-3, 5e-3), colours (1e-3, 1e-3), opacities (8e-3, 6e-3):
  tests/test_basic.py::test_rasterize_to_pixels.
The viewmat's gradient (pose refinement) is the sum over Gaussians of the camera-frame gradients
the means' gradients are made of: it is held to a relative norm error below 1e-2, the means'
rtol (gsplat's own projection-only check, test_projection, holds it to 2e-3).
Both cap alpha at ALPHA_MAX (0.999, gsplat 1.5's own cap); scenes keep every opacity below it.
"""

from __future__ import annotations

import importlib.util

import pytest
import torch

from ogmapping.frames.rotation import exp_so3
from ogmapping.render import Camera, gsplat_backend, rasterize, rasterize_batch
from ogmapping.render.rules import ALPHA_MAX, COVARIANCE_BLUR
from ogmapping.render.views import SplatSet

HAS_GSPLAT = importlib.util.find_spec("gsplat") is not None
WIDTH, HEIGHT = 96, 72  # 72 is not a multiple of the 16-pixel tile: partial tiles are covered
K = torch.tensor([[80.0, 0.0, 48.0], [0.0, 80.0, 36.0], [0.0, 0.0, 1.0]])
PARAMS = ("means", "quats", "scales", "opacities", "colors")
GRAD_TOLERANCES = {  # (rtol, atol), see the module docstring for where each comes from
    "means": (1e-2, 6e-2),
    "quats": (2e-1, 2e-2),
    "scales": (5e-1, 2e-1),
    "opacities": (8e-3, 6e-3),
    "colors": (1e-3, 1e-3),
}


def random_scene(seed: int, n: int = 300) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """Gaussians inside the view of a randomly placed camera; returns them and the world-to-camera matrix."""
    g = torch.Generator().manual_seed(seed)
    z = 1.5 + 2.5 * torch.rand(n, generator=g)
    x = (torch.rand(n, generator=g) - 0.5) * 1.0 * z
    y = (torch.rand(n, generator=g) - 0.5) * 0.7 * z
    turn = 0.3 * torch.randn(3, generator=g)
    c2w = torch.eye(4)
    c2w[:3, :3] = exp_so3(turn)
    c2w[:3, 3] = torch.randn(3, generator=g)
    means = torch.stack([x, y, z], dim=-1) @ c2w[:3, :3].T + c2w[:3, 3]
    scene = {
        "means": means,
        "quats": torch.randn(n, 4, generator=g),
        "scales": torch.exp(torch.empty(n, 3).uniform_(-4.0, -1.5, generator=g)),
        "opacities": torch.empty(n).uniform_(0.05, 0.9, generator=g),
        "colors": torch.rand(n, 3, generator=g),
    }
    return scene, torch.linalg.inv(c2w)


def render(backend: str, scene: dict[str, torch.Tensor], viewmat: torch.Tensor, background,
           blur: float = COVARIANCE_BLUR):
    leaves = {k: v.cuda().requires_grad_() for k, v in scene.items()}
    splats = SplatSet(*(leaves[k] for k in PARAMS))
    out = rasterize(splats, Camera(viewmat.cuda(), K.cuda(), WIDTH, HEIGHT, blur), background, backend=backend)
    return out, leaves


def close(actual: torch.Tensor, expected: torch.Tensor, rtol: float, atol: float, what: str) -> None:
    torch.testing.assert_close(actual, expected, rtol=rtol, atol=atol, msg=lambda m: f"{what}: {m}")


def fail_unless_usable() -> None:
    """gsplat installed but unusable (kernels not built, another version) is a broken install to report."""
    reason = gsplat_backend.unavailable_reason()
    if reason is not None:
        pytest.fail(reason)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.skipif(not HAS_GSPLAT, reason="gsplat is not installed (see docs/cuda.md)")
@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("with_background", [False, True])
@pytest.mark.parametrize("blur", [COVARIANCE_BLUR, COVARIANCE_BLUR / 4])  # the default, a stride-2 tracking render's
def test_gsplat_matches_torch_reference(seed: int, with_background: bool, blur: float) -> None:
    fail_unless_usable()
    scene, viewmat = random_scene(seed)
    background = torch.tensor([0.1, 0.4, 0.8], device="cuda") if with_background else None
    ref, ref_leaves = render("torch", scene, viewmat, background, blur)
    gs, gs_leaves = render("gsplat", scene, viewmat, background, blur)

    assert torch.equal(gs.visible, ref.visible) and bool(ref.visible.all())
    close(gs.color, ref.color, 1e-4, 1e-4, "colour")
    close(gs.alpha, ref.alpha, 1e-4, 1e-4, "alpha")
    # Accumulated depth (what gsplat's test renders): expected depth is ill-conditioned at tiny alpha.
    close(gs.depth * gs.alpha, ref.depth * ref.alpha, 1e-4, 1e-4, "accumulated depth")
    close(gs.means2d, ref.means2d.detach(), 1e-4, 1e-4, "means2d")

    g = torch.Generator(device="cuda").manual_seed(seed)
    v_color = torch.randn(HEIGHT, WIDTH, 3, device="cuda", generator=g)
    v_depth = torch.randn(HEIGHT, WIDTH, device="cuda", generator=g) * ref.alpha.detach()
    v_alpha = torch.randn(HEIGHT, WIDTH, device="cuda", generator=g)
    for out in (ref, gs):
        ((out.color * v_color).sum() + (out.depth * v_depth).sum() + (out.alpha * v_alpha).sum()).backward()

    close(gs.means2d.grad, ref.means2d.grad, 5e-3, 5e-3, "means2d gradient (pixels)")
    for name, (rtol, atol) in GRAD_TOLERANCES.items():
        close(gs_leaves[name].grad, ref_leaves[name].grad, rtol, atol, f"{name} gradient")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.skipif(not HAS_GSPLAT, reason="gsplat is not installed (see docs/cuda.md)")
def test_gsplat_caps_alpha_where_the_reference_does() -> None:
    """One opaque Gaussian over the image centre: both clamp its alpha at ALPHA_MAX there."""
    fail_unless_usable()
    scene = {
        "means": torch.tensor([[0.0, 0.0, 2.0]]),
        "quats": torch.tensor([[1.0, 0.0, 0.0, 0.0]]),
        "scales": torch.tensor([[1.0, 1.0, 1.0]]),
        "opacities": torch.tensor([1.0]),
        "colors": torch.tensor([[0.2, 0.5, 0.9]]),
    }
    ref, _ = render("torch", scene, torch.eye(4), None)
    gs, _ = render("gsplat", scene, torch.eye(4), None)
    assert float(ref.alpha.detach().max()) == pytest.approx(ALPHA_MAX, abs=1e-6)
    close(gs.alpha, ref.alpha, 1e-5, 1e-5, "alpha")
    close(gs.color, ref.color, 1e-5, 1e-5, "colour")


def test_missing_gsplat_names_the_install_command() -> None:
    """Without gsplat the backend fails at call time with the pip command, not at import time."""
    if HAS_GSPLAT:
        pytest.skip("gsplat is installed")
    scene, viewmat = random_scene(0, n=4)
    with pytest.raises(ImportError, match=r"gsplat is not installed.*pip install"):
        rasterize(SplatSet(*(scene[k] for k in PARAMS)), Camera(viewmat, K, WIDTH, HEIGHT), backend="gsplat")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.skipif(not HAS_GSPLAT, reason="gsplat is not installed (see docs/cuda.md)")
def test_gsplat_batch_matches_torch_reference() -> None:
    """Four views, two image sizes (two gsplat calls), different counts (padding) against the reference."""
    fail_unless_usable()
    half = K.clone()
    half[:2] *= 0.5
    sizes = ((WIDTH, HEIGHT, K), (WIDTH // 2, HEIGHT // 2, half), (WIDTH, HEIGHT, K), (WIDTH // 2, HEIGHT // 2, half))
    counts = (300, 120, 200, 0)
    results = {}
    for backend in ("torch", "gsplat"):
        scenes, cameras, leaves = [], [], []
        for seed, ((width, height, intrinsics), n) in enumerate(zip(sizes, counts, strict=True)):
            scene, viewmat = random_scene(seed, max(n, 1))
            view_leaves = {k: v[:n].cuda().requires_grad_() for k, v in scene.items()}
            leaves.append(view_leaves)
            scenes.append(SplatSet(*(view_leaves[k] for k in PARAMS)))
            cameras.append(Camera(viewmat.cuda(), intrinsics.cuda(), width, height))
        outputs = rasterize_batch(scenes, cameras, torch.tensor([0.1, 0.4, 0.8], device="cuda"), backend=backend)
        g = torch.Generator(device="cuda").manual_seed(0)
        loss = sum((out.color * torch.randn(out.color.shape, device="cuda", generator=g)).sum()
                   + (out.alpha * torch.randn(out.alpha.shape, device="cuda", generator=g)).sum() for out in outputs)
        loss.backward()
        results[backend] = outputs, leaves
    (ref, ref_leaves), (gs, gs_leaves) = results["torch"], results["gsplat"]
    for v in range(len(sizes)):
        assert gs[v].color.shape == ref[v].color.shape and torch.equal(gs[v].visible, ref[v].visible), v
        close(gs[v].color, ref[v].color, 1e-4, 1e-4, f"view {v} colour")
        close(gs[v].alpha, ref[v].alpha, 1e-4, 1e-4, f"view {v} alpha")
        close(gs[v].depth * gs[v].alpha, ref[v].depth * ref[v].alpha, 1e-4, 1e-4, f"view {v} accumulated depth")
        if counts[v]:
            close(gs[v].means2d.grad, ref[v].means2d.grad, 5e-3, 5e-3, f"view {v} means2d gradient")
            for name, (rtol, atol) in GRAD_TOLERANCES.items():
                close(gs_leaves[v][name].grad, ref_leaves[v][name].grad, rtol, atol, f"view {v} {name} gradient")


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.skipif(not HAS_GSPLAT, reason="gsplat is not installed (see docs/cuda.md)")
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gsplat_viewmat_gradients_match_torch_reference(seed: int) -> None:
    """Three views (two image sizes, so two gsplat calls) with poses to refine, a fourth fixed."""
    fail_unless_usable()
    half = K.clone()
    half[:2] *= 0.5
    sizes = ((WIDTH, HEIGHT, K), (WIDTH // 2, HEIGHT // 2, half), (WIDTH, HEIGHT, K), (WIDTH, HEIGHT, K))
    posed = (True, True, True, False)
    gradients = {}
    for backend in ("torch", "gsplat"):
        scenes, cameras = [], []
        for view, (width, height, intrinsics) in enumerate(sizes):
            scene, viewmat = random_scene(3 * seed + view, 200)
            scenes.append(SplatSet(*(scene[k].cuda().requires_grad_() for k in PARAMS)))
            cameras.append(Camera(viewmat.cuda().requires_grad_(posed[view]), intrinsics.cuda(), width, height))
        outputs = rasterize_batch(scenes, cameras, None, backend=backend)
        g = torch.Generator(device="cuda").manual_seed(seed)
        loss = sum((out.color * torch.randn(out.color.shape, device="cuda", generator=g)).sum()
                   + (out.depth * torch.randn(out.depth.shape, device="cuda", generator=g) * out.alpha.detach()).sum()
                   + (out.alpha * torch.randn(out.alpha.shape, device="cuda", generator=g)).sum() for out in outputs)
        loss.backward()
        gradients[backend] = [camera.viewmat.grad for camera in cameras]
    for view, (ref, gs) in enumerate(zip(gradients["torch"], gradients["gsplat"], strict=True)):
        if not posed[view]:
            assert ref is None and gs is None, view
            continue
        assert gs.shape == (4, 4) and gs.dtype == ref.dtype and not bool(gs[3].any()), view
        error = float((gs - ref).norm() / ref.norm())
        assert error < 1e-2, (view, error, gs, ref)
