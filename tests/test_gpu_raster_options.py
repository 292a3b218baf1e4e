"""gsplat's options (``RasterOptions``) and selective Adam on a GPU, against the classic unpacked render and
Adam's step on the host: what the stand-ins of test_gsplat_backend.py and test_selective_adam.py cannot show."""

from __future__ import annotations

import pytest
import torch
from test_gpu_gsplat import HAS_GSPLAT, HEIGHT, PARAMS, WIDTH, K, close, fail_unless_usable, random_scene

from ogmapping.optim.selective_adam import SelectiveAdam
from ogmapping.render import Camera, RasterOptions, rasterize_batch
from ogmapping.render.views import SplatSet

pytestmark = [
    pytest.mark.gpu,
    pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
]
needs_gsplat = pytest.mark.skipif(not HAS_GSPLAT, reason="gsplat is not installed (see docs/cuda.md)")


def render_views(options: RasterOptions, seed: int = 0):
    """Three posed views (their viewmats require grad) of 300, 200 and 250 Gaussians rendered by gsplat in one
    batch and backpropagated: the outputs, each view's leaves and the viewmats."""
    fail_unless_usable()
    scenes, cameras, leaves, viewmats = [], [], [], []
    for view, n in enumerate((300, 200, 250)):
        scene, viewmat = random_scene(3 * seed + view, n)
        view_leaves = {k: v.cuda().requires_grad_() for k, v in scene.items()}
        leaves.append(view_leaves)
        scenes.append(SplatSet(*(view_leaves[k] for k in PARAMS)))
        viewmats.append(viewmat.cuda().requires_grad_())
        cameras.append(Camera(viewmats[-1], K.cuda(), WIDTH, HEIGHT))
    outputs = rasterize_batch(scenes, cameras, None, backend="gsplat", options=options)
    g = torch.Generator(device="cuda").manual_seed(seed)
    loss = sum((out.color * torch.randn(out.color.shape, device="cuda", generator=g)).sum()
               + (out.alpha * torch.randn(out.alpha.shape, device="cuda", generator=g)).sum() for out in outputs)
    loss.backward()
    return outputs, leaves, viewmats


@needs_gsplat
@pytest.mark.parametrize("seed", [0, 1])
def test_packed_renders_and_differentiates_as_unpacked(seed: int) -> None:
    """One gsplat call a view, so each view's means and viewmat gradients are its own, as unpacked."""
    plain, plain_leaves, plain_viewmats = render_views(RasterOptions(), seed)
    packed, packed_leaves, packed_viewmats = render_views(RasterOptions(packed=True), seed)
    for v, (a, b) in enumerate(zip(packed, plain, strict=True)):
        assert torch.equal(a.visible, b.visible), v
        for name in ("color", "alpha", "means2d"):
            close(getattr(a, name), getattr(b, name), 1e-5, 1e-5, f"view {v} {name}")
        close(a.means2d.grad, b.means2d.grad, 1e-4, 1e-5, f"view {v} means2d gradient")
        for name in PARAMS:
            close(packed_leaves[v][name].grad, plain_leaves[v][name].grad, 1e-4, 1e-5, f"view {v} {name} gradient")
        close(packed_viewmats[v].grad, plain_viewmats[v].grad, 1e-4, 1e-4, f"view {v} viewmat gradient")


@needs_gsplat
@pytest.mark.parametrize("packed", [False, True])
def test_absgrad_bounds_the_gradient_and_leaves_it_as_it_was(packed: bool) -> None:
    """The summed absolute gradient is at least the gradient's absolute value (0 where culled), and asking
    for it changes neither the images nor the gradient."""
    plain, _, _ = render_views(RasterOptions(packed=packed))
    absolute, _, _ = render_views(RasterOptions(packed=packed, absgrad=True))
    for v, (a, b) in enumerate(zip(absolute, plain, strict=True)):
        close(a.color, b.color, 0, 0, f"view {v} colour")
        close(a.means2d.grad, b.means2d.grad, 1e-5, 1e-6, f"view {v} means2d gradient")
        summed, grad = a.screen_gradient(absolute=True), a.screen_gradient()
        assert summed is not None and summed.shape == grad.shape, v
        assert bool((summed >= grad.abs() * (1 - 1e-5) - 1e-8).all()), v
        assert not bool(summed[~a.visible].any()) and bool(summed[a.visible].any()), v
        assert b.screen_gradient(absolute=True) is None


@needs_gsplat
def test_antialiased_only_lowers_opacity() -> None:
    """The compensation scales each Gaussian's opacity by at most 1: alpha never rises, and falls somewhere."""
    classic, _, _ = render_views(RasterOptions())
    antialiased, _, _ = render_views(RasterOptions(antialiased=True))
    for v, (a, b) in enumerate(zip(antialiased, classic, strict=True)):
        assert bool((a.alpha <= b.alpha + 1e-5).all()), v
        assert bool((a.alpha < b.alpha - 1e-4).any()), v


def test_selective_adam_with_its_count_on_the_device_steps_as_on_the_host() -> None:
    """Fused on CUDA the step count stays on the device (torch's capturable formulas, never read by the host):
    the rows seen step as the CPU's Adam steps them, the others keep values and moments."""
    generator = torch.Generator().manual_seed(0)
    values = torch.randn(4096, 3, generator=generator)
    visible = torch.rand(4096, generator=generator) < 0.4
    grads = [torch.randn(4096, 3, generator=generator) for _ in range(3)]
    results = []
    for device, fused in (("cpu", None), ("cuda", True)):
        param = torch.nn.Parameter(values.to(device))
        adam = SelectiveAdam([{"params": [param], "lr": 0.01, "name": "rows"}], row_groups=["rows"], eps=1e-15,
                             fused=fused)
        for grad in grads:
            param.grad = grad.to(device)
            adam.select(visible.to(device))
            adam.step()
        state = adam.state[param]
        assert state["step"].device.type == device
        results.append([tensor.detach().cpu() for tensor in (param, state["exp_avg"], state["exp_avg_sq"])])
    for host, on_device in zip(*results, strict=True):
        close(on_device, host, 1e-5, 1e-7, "values and moments")
        assert torch.equal(on_device[~visible], host[~visible])
