"""The gsplat backend's decisions and its wrapping of gsplat's call, checked on the CPU with stand-ins for gsplat.

Which backend ``auto`` picks, when gsplat counts as usable (gsplat 1.5 reports kernels it could not
build only by setting ``gsplat.cuda._backend._C`` to None) and what ``render_group`` does around
``gsplat.rasterization`` (views padded into one batch and cut out again, float32 in, the caller's
dtype out, culled ``means2d`` zero, each view's screen-space and viewmat gradients its own), and how the
options (``RasterOptions``) reach gsplat: packed outputs unpacked into the same output, the absolute
gradient read per view. The real kernels are checked against the reference in ``test_gpu_gsplat.py``.
"""

from __future__ import annotations

import sys
import types

import pytest
import torch

from ogmapping.render import RasterOptions, gsplat_backend, rasterize, resolve_backend
from ogmapping.render.views import Camera, SplatSet

CUDA = torch.device("cuda")


@pytest.fixture
def fresh_check():
    """``unavailable_reason`` is cached per process; each test here judges its own stand-in."""
    gsplat_backend.unavailable_reason.cache_clear()
    yield gsplat_backend.unavailable_reason
    gsplat_backend.unavailable_reason.cache_clear()


def install_fake_gsplat(monkeypatch, version: str, compiled: object | None) -> None:
    """Stand-in ``gsplat``, ``gsplat.cuda`` and ``gsplat.cuda._backend`` modules; ``compiled`` becomes ``_C``."""
    package, cuda, backend = (types.ModuleType(name) for name in ("gsplat", "gsplat.cuda", "gsplat.cuda._backend"))
    package.__version__ = version
    backend._C = compiled
    for module in (package, cuda, backend):
        monkeypatch.setitem(sys.modules, module.__name__, module)


def test_missing_gsplat_is_unusable(monkeypatch, fresh_check):
    monkeypatch.setitem(sys.modules, "gsplat", None)
    assert fresh_check().startswith("gsplat is not installed")


def test_gsplat_without_compiled_kernels_is_unusable(monkeypatch, fresh_check):
    install_fake_gsplat(monkeypatch, "1.5.3", compiled=None)
    assert "without compiled CUDA kernels" in fresh_check()


def test_gsplat_whose_kernels_fail_to_load_is_unusable(monkeypatch, fresh_check):
    install_fake_gsplat(monkeypatch, "1.5.3", compiled=None)
    monkeypatch.setitem(sys.modules, "gsplat.cuda._backend", None)  # its import raises
    assert "could not load its CUDA kernels" in fresh_check()


@pytest.mark.parametrize("version", ["1.4.0", "1.6.0"])
def test_gsplat_of_another_minor_version_is_unusable(monkeypatch, fresh_check, version):
    install_fake_gsplat(monkeypatch, version, compiled=object())
    assert f"gsplat {version} is installed" in fresh_check()


def test_gsplat_before_batched_rendering_is_unusable(monkeypatch, fresh_check):
    install_fake_gsplat(monkeypatch, "1.5.2", compiled=object())
    assert "through gsplat >= 1.5.3" in fresh_check()


def test_gsplat_1_5_with_kernels_is_usable(monkeypatch, fresh_check):
    install_fake_gsplat(monkeypatch, "1.5.3", compiled=object())
    assert fresh_check() is None


def unusable(monkeypatch, reason: str | None) -> None:
    monkeypatch.setattr(gsplat_backend, "unavailable_reason", lambda: reason)


def test_auto_on_cuda_picks_gsplat_when_it_can_render(monkeypatch, recwarn):
    unusable(monkeypatch, None)
    assert resolve_backend("auto", CUDA) == "gsplat"
    assert not recwarn.list


def test_auto_on_cuda_falls_back_to_the_reference_with_a_warning(monkeypatch):
    unusable(monkeypatch, "gsplat 1.5.3 is installed without compiled CUDA kernels")
    with pytest.warns(RuntimeWarning, match="without compiled CUDA kernels.*pure-torch reference.*seconds per"):
        assert resolve_backend("auto", CUDA) == "torch"


def test_auto_on_the_cpu_never_asks_for_gsplat(monkeypatch, recwarn):
    monkeypatch.setattr(gsplat_backend, "unavailable_reason", lambda: pytest.fail("gsplat was consulted"))
    assert resolve_backend("auto", torch.device("cpu")) == "cpu"
    assert not recwarn.list


def test_gsplat_by_name_fails_now_with_the_reason_and_the_install_hint(monkeypatch):
    unusable(monkeypatch, "gsplat 1.5.3 is installed without compiled CUDA kernels")
    with pytest.raises(ImportError, match=r"without compiled CUDA kernels; .*--no-binary gsplat"):
        resolve_backend("gsplat", CUDA)
    unusable(monkeypatch, None)
    assert resolve_backend("gsplat", CUDA) == "gsplat"


class WarpSummedCameraFrame(torch.autograd.Function):
    """Means into each entry's camera frame, with the reduction of gsplat 1.5.3's projection backward
    (ProjectionEWA3DGSFused.cu): one thread per (entry, Gaussian) in order, the viewmat's gradient
    summed over a warp's active threads grouped by camera index (always 0 here), not by entry, and
    the sum added to the entry of the group's first thread."""

    @staticmethod
    def forward(ctx, means: torch.Tensor, viewmats: torch.Tensor, active: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(means, viewmats, active)
        return means @ viewmats[:, 0, :3, :3].transpose(1, 2) + viewmats[:, 0, None, :3, 3]

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        means, viewmats, active = ctx.saved_tensors
        batch, n = active.shape
        per_thread = torch.zeros(batch, n, 4, 4, dtype=grad.dtype)
        per_thread[..., :3, :3] = grad[..., :, None] * means[..., None, :]
        per_thread[..., :3, 3] = grad
        per_thread = (per_thread * active[..., None, None]).reshape(batch * n, 4, 4)
        lanes_active = active.reshape(-1)
        v_viewmats = torch.zeros_like(viewmats)
        for start in range(0, batch * n, 32):
            lanes = torch.nonzero(lanes_active[start:start + 32]).flatten() + start
            if len(lanes):
                v_viewmats[int(lanes[0]) // n, 0] += per_thread[lanes].sum(dim=0)
        return grad @ viewmats[:, 0, :3, :3], v_viewmats, None


class AbsGradTap(torch.autograd.Function):
    """Passes ``means2d`` on; in backward sets ``means2d.absgrad`` as gsplat's rasterizer does with
    ``absgrad=True`` (here 3 |gradient| + 1, which no plain gradient equals)."""

    @staticmethod
    def forward(ctx, means2d: torch.Tensor, absgrad: bool) -> torch.Tensor:
        ctx.save_for_backward(means2d)
        ctx.absgrad = absgrad
        return means2d.clone()

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        (means2d,) = ctx.saved_tensors
        if ctx.absgrad:
            means2d.absgrad = 3 * grad.abs() + 1
        return grad, None


def fake_rasterization(culled: torch.Tensor, calls: list[dict] | None = None):
    """A stand-in for ``gsplat.rasterization`` with its output shapes (``RGB+ED``, a leading batch dimension
    B and one camera per batch entry; ``packed=True``: ``means2d`` (nnz, 2), ``radii`` (nnz, 2) with
    ``batch_ids`` and ``gaussian_ids``): it takes float32 only, as gsplat's kernels do, leaves culled
    ``means2d`` rows as garbage, reduces the viewmats' gradient as gsplat does (``WarpSummedCameraFrame``)
    and with ``absgrad`` sets ``meta["means2d"].absgrad`` in backward. ``culled`` (B, N) marks the culled;
    rows past N, the padding, are culled too. Each call's options are appended to ``calls``."""

    def rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **options):
        for tensor in (means, quats, scales, opacities, colors, viewmats, Ks):
            assert tensor.dtype == torch.float32
        assert options["render_mode"] == "RGB+ED"
        if calls is not None:
            calls.append(options)
        batch, n = means.shape[:2]
        assert viewmats.shape == (batch, 1, 4, 4) and Ks.shape == (batch, 1, 3, 3)
        hidden = torch.ones(batch, n, dtype=torch.bool)
        hidden[:, :culled.shape[1]] = culled
        camera = WarpSummedCameraFrame.apply(means, viewmats, ~hidden)
        projected = camera[..., :2] * Ks[:, :, 0, 0, None] / camera[..., 2:] + Ks[:, 0, None, :2, 2]
        radii = torch.where(hidden, 0, 3).to(torch.int32)[..., None].expand(batch, n, 2)
        if options["packed"]:
            batch_ids, gaussian_ids = torch.nonzero(~hidden, as_tuple=True)
            means2d, radii = projected[batch_ids, gaussian_ids], radii[batch_ids, gaussian_ids]
            meta = {"batch_ids": batch_ids, "camera_ids": torch.zeros_like(batch_ids), "gaussian_ids": gaussian_ids}
            tapped = AbsGradTap.apply(means2d, options["absgrad"])
            kept = [tapped[batch_ids == b] for b in range(batch)]
        else:
            means2d = torch.where(hidden.unsqueeze(-1), torch.full_like(projected, 1e30), projected)[:, None]
            meta, radii = {}, radii[:, None]
            tapped = AbsGradTap.apply(means2d, options["absgrad"])
            kept = [tapped[b, 0, ~hidden[b]] for b in range(batch)]
        weight = torch.stack([(kept[b].sum() + opacities[b].sum() + colors[b].sum()) * 1e-3 * (b + 1)
                              for b in range(batch)])
        render = weight[:, None, None, None, None] * torch.ones(batch, 1, height, width, 4)
        alpha = torch.sigmoid(weight)[:, None, None, None, None] * torch.ones(batch, 1, height, width, 1)
        return render, alpha, {**meta, "means2d": means2d, "radii": radii}

    return rasterization


def random_scene(generator: torch.Generator, n: int) -> SplatSet:
    def leaf(*shape: int) -> torch.Tensor:
        return torch.rand(*shape, generator=generator, dtype=torch.float64).requires_grad_(True)

    scene = SplatSet(leaf(n, 3), leaf(n, 4), leaf(n, 3), leaf(n), leaf(n, 3))
    with torch.no_grad():
        scene.means[:, 2] += 1.0
    return scene


def test_render_group_pads_views_casts_to_float32_and_back_and_zeroes_culled_means2d():
    generator = torch.Generator().manual_seed(0)
    counts, width, height = (5, 2), 8, 6
    scenes = [random_scene(generator, n) for n in counts]
    # Padding (the second view's last three) is culled too, as gsplat culls opacity 0.
    culled = torch.tensor([[False, True, False, False, True], [False, True, True, True, True]])
    K = torch.tensor([[10.0, 0.0, 4.0], [0.0, 10.0, 3.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    cameras = [Camera(torch.eye(4, dtype=torch.float64), K, width, height) for _ in scenes]
    outputs = gsplat_backend.render_group(fake_rasterization(culled), scenes, cameras, None)

    assert len(outputs) == 2
    (sum(o.color.sum() + o.depth.sum() + o.alpha.sum() for o in outputs)).backward()
    for b, (output, scene) in enumerate(zip(outputs, scenes, strict=True)):
        n, view_culled = counts[b], culled[b, :counts[b]]
        for image in (output.color, output.depth, output.alpha, output.means2d):
            assert image.dtype == torch.float64
        assert output.color.shape == (height, width, 3) and output.depth.shape == output.alpha.shape == (height, width)
        assert output.means2d.shape == (n, 2) and torch.equal(output.visible, ~view_culled)
        assert torch.equal(output.means2d[view_culled], torch.zeros(int(view_culled.sum()), 2, dtype=torch.float64))
        assert bool(torch.isfinite(output.means2d).all())
        grad = output.means2d.grad
        assert grad.dtype == torch.float64 and grad.shape == (n, 2)
        assert bool((grad[~view_culled] != 0).all()) and bool((grad[view_culled] == 0).all())
        for name in ("means", "opacities", "colors"):
            leaf = getattr(scene, name)
            assert leaf.grad is not None and leaf.grad.dtype == torch.float64, name
    # Each view's screen gradient is its own: the fake weighs view b by b + 1.
    assert bool((outputs[1].means2d.grad[0] > 1.5 * outputs[0].means2d.grad[0]).all())


def test_render_group_routes_each_viewmat_its_gradient():
    """Viewmats that require grad (refined poses) get their own view's gradient, in their dtype;
    a fixed one in the same batch gets none."""
    generator = torch.Generator().manual_seed(1)
    scene = random_scene(generator, 4)
    K = torch.tensor([[10.0, 0.0, 4.0], [0.0, 10.0, 3.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, 3] = torch.tensor([0.1, -0.2, 0.3])
    viewmats = [pose.clone().requires_grad_(posed) for posed in (False, True, True)]
    culled = torch.tensor([[False, True, False, False]] * 3)
    outputs = gsplat_backend.render_group(fake_rasterization(culled), [scene] * 3,
                                          [Camera(viewmat, K, 8, 6) for viewmat in viewmats], None)
    sum(output.color.sum() for output in outputs).backward()
    assert viewmats[0].grad is None
    for viewmat in viewmats[1:]:
        assert viewmat.grad.dtype == torch.float64 and viewmat.grad.shape == (4, 4)
        assert bool(viewmat.grad[:3].any()) and not bool(viewmat.grad[3].any())
    # Identical views, the fake weighing view b by b + 1: each gradient is its own view's.
    torch.testing.assert_close(viewmats[2].grad, 1.5 * viewmats[1].grad, rtol=1e-5, atol=0)


def batched_and_alone_viewmat_gradients(counts: tuple[int, ...]) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Each view's viewmat gradient rendered in one batch, and rendered as a batch of one."""
    generator = torch.Generator().manual_seed(2)
    scenes = [random_scene(generator, n) for n in counts]
    K = torch.tensor([[10.0, 0.0, 4.0], [0.0, 10.0, 3.0], [0.0, 0.0, 1.0]], dtype=torch.float64)

    def gradients(group: list[int]) -> list[torch.Tensor]:
        viewmats = [torch.eye(4, dtype=torch.float64).requires_grad_() for _ in group]
        padding = torch.arange(max(counts[i] for i in group)) >= torch.tensor([[counts[i]] for i in group])
        outputs = gsplat_backend.render_group(fake_rasterization(padding), [scenes[i] for i in group],
                                              [Camera(viewmat, K, 8, 6) for viewmat in viewmats], None)
        sum(output.color.sum() for output in outputs).backward()
        return [viewmat.grad for viewmat in viewmats]

    return gradients(list(range(len(counts)))), [gradients([i])[0] for i in range(len(counts))]


def test_each_batch_entry_holds_whole_warps_so_its_viewmat_gradient_is_its_own():
    assert gsplat_backend.batch_rows([20]) == 20
    assert gsplat_backend.batch_rows([20, 7, 33]) == 64
    assert gsplat_backend.batch_rows([32, 32]) == 32
    batched, alone = batched_and_alone_viewmat_gradients((40, 7, 45))
    for b, (in_batch, by_itself) in enumerate(zip(batched, alone, strict=True)):
        # The fake weighs entry b by b + 1; rendered alone, a view is entry 0.
        torch.testing.assert_close(in_batch, (b + 1) * by_itself, rtol=1e-5, atol=1e-9)


def test_entries_that_split_a_warp_would_mix_their_viewmat_gradients(monkeypatch):
    """The stand-in reproduces what whole warps prevent: rows of the largest count alone."""
    monkeypatch.setattr(gsplat_backend, "batch_rows", max)
    batched, alone = batched_and_alone_viewmat_gradients((40, 7, 45))
    assert not torch.allclose(batched[0], alone[0], rtol=1e-3)


def test_views_are_grouped_by_image_size_and_blur_in_order_of_appearance():
    def camera(width: int, height: int, blur: float = 0.3) -> Camera:
        return Camera(torch.eye(4), torch.eye(3), width, height, blur)

    cameras = [camera(64, 48), camera(32, 24), camera(64, 48), camera(32, 24), camera(16, 16), camera(64, 48, 0.075)]
    assert gsplat_backend.call_groups(cameras) == [[0, 2], [1, 3], [4], [5]]
    # packed, one view a call: gsplat's packed backward would mix the entries' gradients mid-warp
    assert gsplat_backend.call_groups(cameras, packed=True) == [[index] for index in range(6)]


def test_a_group_without_gaussians_renders_the_background():
    background = torch.tensor([0.2, 0.4, 0.6])
    empty = SplatSet(*(torch.zeros(0, *shape) for shape in ((3,), (4,), (3,), (), (3,))))
    outputs = gsplat_backend.render_group(fake_rasterization(torch.zeros(2, 0, dtype=torch.bool)), [empty, empty],
                                          [Camera(torch.eye(4), torch.eye(3), 4, 3)] * 2, background)
    for output in outputs:
        assert torch.equal(output.color, background.expand(3, 4, 3)) and not bool(output.alpha.any())


def render_options(options: RasterOptions) -> tuple[list, list[SplatSet], list[torch.Tensor], list[dict]]:
    """Two views of 5 and 2 Gaussians rendered by the stand-in with ``options`` and backpropagated: the
    outputs, the scenes, the viewmats (which require grad) and the options each call passed."""
    generator = torch.Generator().manual_seed(5)
    scenes = [random_scene(generator, n) for n in (5, 2)]
    culled = torch.tensor([[False, True, False, False, True], [False, True, True, True, True]])
    K = torch.tensor([[10.0, 0.0, 4.0], [0.0, 10.0, 3.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    viewmats = [torch.eye(4, dtype=torch.float64).requires_grad_() for _ in scenes]
    calls: list[dict] = []
    outputs = gsplat_backend.render_group(fake_rasterization(culled, calls), scenes,
                                          [Camera(viewmat, K, 8, 6) for viewmat in viewmats], None, options)
    (sum(o.color.sum() + o.depth.sum() + o.alpha.sum() for o in outputs)).backward()
    return outputs, scenes, viewmats, calls


def test_the_options_reach_gsplat():
    *_, calls = render_options(RasterOptions())
    assert [(c["packed"], c["absgrad"], c["rasterize_mode"]) for c in calls] == [(False, False, "classic")]
    *_, calls = render_options(RasterOptions(packed=True, absgrad=True, antialiased=True))
    assert [(c["packed"], c["absgrad"], c["rasterize_mode"]) for c in calls] == [(True, True, "antialiased")]


def test_packed_outputs_are_unpacked_into_the_same_render_output():
    """gsplat's packed layout (only the kept (entry, Gaussian) pairs, with their ids) comes back as the
    unpacked layout's output: images, ``means2d`` and ``visible``, and every gradient."""
    unpacked, scenes, viewmats, _ = render_options(RasterOptions())
    packed, packed_scenes, packed_viewmats, _ = render_options(RasterOptions(packed=True))
    for plain, output in zip(unpacked, packed, strict=True):
        for name in ("color", "depth", "alpha", "means2d", "visible"):
            got, want = getattr(output, name), getattr(plain, name)
            assert got.shape == want.shape and got.dtype == want.dtype, name
            torch.testing.assert_close(got, want, msg=name)
        torch.testing.assert_close(output.means2d.grad, plain.means2d.grad)
        assert output.screen_gradient(absolute=True) is None  # absgrad off
    for scene, packed_scene in zip(scenes, packed_scenes, strict=True):
        for name in ("means", "quats", "scales", "opacities", "colors"):
            torch.testing.assert_close(getattr(packed_scene, name).grad, getattr(scene, name).grad, msg=name)
    for viewmat, packed_viewmat in zip(viewmats, packed_viewmats, strict=True):
        torch.testing.assert_close(packed_viewmat.grad, viewmat.grad)


@pytest.mark.parametrize("packed", [False, True])
def test_absgrad_is_read_per_view_after_backward(packed: bool):
    """``screen_gradient(absolute=True)`` is each view's part of gsplat's ``meta["means2d"].absgrad`` (the
    stand-in's 3 |gradient| + 1), 0 where culled; ``screen_gradient()`` stays the gradient."""
    outputs, *_ = render_options(RasterOptions(packed=packed, absgrad=True))
    for output in outputs:
        absolute, grad = output.screen_gradient(absolute=True), output.screen_gradient()
        assert absolute.dtype == torch.float64 and absolute.shape == grad.shape
        seen = output.visible.unsqueeze(-1)
        torch.testing.assert_close(absolute, torch.where(seen, 3 * grad.abs() + 1, 0.0))


def test_other_backends_refuse_gsplat_only_options_and_render_packed_as_ever():
    generator = torch.Generator().manual_seed(6)
    scene = random_scene(generator, 3)
    K = torch.tensor([[10.0, 0.0, 4.0], [0.0, 10.0, 3.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    camera = Camera(torch.eye(4, dtype=torch.float64), K, 8, 6)
    for options in (RasterOptions(absgrad=True), RasterOptions(antialiased=True)):
        with pytest.raises(ValueError, match=r"gsplat.s options only .* the torch backend"):
            rasterize(scene, camera, backend="torch", options=options)
    packed = rasterize(scene, camera, backend="torch", options=RasterOptions(packed=True))
    assert torch.equal(packed.color, rasterize(scene, camera, backend="torch").color)
