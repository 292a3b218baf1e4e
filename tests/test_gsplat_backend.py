"""The gsplat backend's decisions and its wrapping of gsplat's call, checked on the CPU with stand-ins for gsplat.

Which backend ``auto`` picks, when gsplat counts as usable (gsplat 1.5 reports kernels it could not
build only by setting ``gsplat.cuda._backend._C`` to None) and what ``render_with`` does around
``gsplat.rasterization`` (float32 in, the caller's dtype out, culled ``means2d`` zero). The real
kernels are checked against the reference in ``test_gpu_gsplat.py``.
"""

from __future__ import annotations

import sys
import types

import pytest
import torch

from ogmapping.render import gsplat_backend, resolve_backend

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


def fake_rasterization(culled: torch.Tensor):
    """A stand-in for ``gsplat.rasterization`` with its output shapes (``packed=False``, ``RGB+ED``, one
    camera): it takes float32 only, as gsplat's kernels do, and leaves culled ``means2d`` rows as garbage."""

    def rasterization(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **options):
        for tensor in (means, quats, scales, opacities, colors, viewmats, Ks):
            assert tensor.dtype == torch.float32
        assert options["packed"] is False and options["render_mode"] == "RGB+ED"
        projected = means[:, :2] * Ks[0, 0, 0] / means[:, 2:] + Ks[0, :2, 2]
        means2d = torch.where(culled.unsqueeze(-1), torch.full_like(projected, 1e30), projected)[None]
        weight = (means2d[0, ~culled].sum() + opacities.sum() + colors.sum()) * 1e-3
        render = weight * torch.ones(1, height, width, 4)
        alpha = torch.sigmoid(weight) * torch.ones(1, height, width, 1)
        radii = torch.where(culled, 0, 3).to(torch.int32)[None, :, None].expand(1, -1, 2)
        return render, alpha, {"means2d": means2d, "radii": radii}

    return rasterization


def test_render_with_casts_to_float32_and_back_and_zeroes_culled_means2d():
    generator = torch.Generator().manual_seed(0)
    n, width, height = 5, 8, 6
    leaves = {
        "means": torch.rand(n, 3, generator=generator, dtype=torch.float64) + torch.tensor([0.0, 0.0, 1.0],
                                                                                           dtype=torch.float64),
        "quats": torch.rand(n, 4, generator=generator, dtype=torch.float64),
        "scales": torch.rand(n, 3, generator=generator, dtype=torch.float64),
        "opacities": torch.rand(n, generator=generator, dtype=torch.float64),
        "colors": torch.rand(n, 3, generator=generator, dtype=torch.float64),
    }
    for tensor in leaves.values():
        tensor.requires_grad_(True)
    culled = torch.tensor([False, True, False, False, True])
    K = torch.tensor([[10.0, 0.0, 4.0], [0.0, 10.0, 3.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    output = gsplat_backend.render_with(fake_rasterization(culled), tuple(leaves.values()),
                                        torch.eye(4, dtype=torch.float64), K, width, height, None)

    for image in (output.color, output.depth, output.alpha, output.means2d):
        assert image.dtype == torch.float64
    assert output.color.shape == (height, width, 3) and output.depth.shape == output.alpha.shape == (height, width)
    assert torch.equal(output.visible, ~culled)
    assert torch.equal(output.means2d[culled], torch.zeros(2, 2, dtype=torch.float64))
    assert bool(torch.isfinite(output.means2d).all())

    (output.color.sum() + output.depth.sum() + output.alpha.sum()).backward()
    assert output.means2d.grad.dtype == torch.float64
    assert bool((output.means2d.grad[~culled] != 0).all()) and bool((output.means2d.grad[culled] == 0).all())
    for name in ("means", "opacities", "colors"):
        assert leaves[name].grad is not None and leaves[name].grad.dtype == torch.float64, name
