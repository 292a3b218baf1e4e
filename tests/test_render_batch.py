"""Batched rendering against one render per view: the compiled cpu backend against the reference.

``rasterize_batch`` renders scene i into camera i. The reference defines it as one ``rasterize``
per view; the cpu backend projects and composites the whole batch in one autograd node each. Its
images and gradients must be those of the reference (relative norm error below 1e-4, the cpu
rasterizer's tolerance, tests/test_render_cpu.py) and exactly those of the cpu backend rendering
each view alone. Views differ in size, pose, blur and Gaussian count (one has none). With poses to
refine, each view's viewmat gets its own gradient, the reference's, and every other output and
gradient stays what it is with fixed poses.
"""

from __future__ import annotations

import ogmapping  # noqa: F401  (first: sets OMP_WAIT_POLICY before torch starts its thread pool)

# isort: split
import pytest
import torch
from test_render_cpu import TOLERANCE, intrinsics, mixed_scene, relative_error

from ogmapping.frames.rotation import exp_so3
from ogmapping.render import Camera, rasterize, rasterize_batch
from ogmapping.render.views import SplatSet

PARAMS = ("means", "quats", "scales", "opacities", "colors")
# seed, Gaussians, size, blur (the default, and a stride-2 tracking render's)
VIEWS = ((0, 300, 64, 48, 0.3), (1, 500, 64, 48, 0.075), (2, 0, 64, 48, 0.3), (3, 400, 53, 37, 0.3))


def pose(seed: int) -> torch.Tensor:
    """A world-to-camera matrix near the identity, so the mixed scenes stay mostly in view."""
    g = torch.Generator().manual_seed(100 + seed)
    turn = 0.05 * torch.randn(3, generator=g)
    viewmat = torch.eye(4)
    viewmat[:3, :3] = exp_so3(turn)
    viewmat[:3, 3] = 0.05 * torch.randn(3, generator=g)
    return viewmat


def views(dtype: torch.dtype, posed: bool = False) -> tuple[list[SplatSet], list[Camera]]:
    """The scenes and cameras of VIEWS; with ``posed`` every viewmat is a leaf that requires grad."""
    scenes, cameras = [], []
    for seed, n, width, height, blur in VIEWS:
        scene = {k: v.to(dtype).clone().requires_grad_(True) for k, v in mixed_scene(seed, max(n, 1), width,
                                                                                       height).items()}
        scenes.append(SplatSet(*(scene[k][:n] if n else scene[k][:0] for k in PARAMS)))
        for k in PARAMS:
            getattr(scenes[-1], k).retain_grad()
        viewmat = pose(seed).to(dtype).requires_grad_(posed)
        cameras.append(Camera(viewmat, intrinsics(width, height).to(dtype), width, height, blur))
    return scenes, cameras


def weighted_loss(outputs) -> torch.Tensor:
    g = torch.Generator().manual_seed(7)
    total = 0
    for out in outputs:
        for image in (out.color, out.depth, out.alpha):
            total = total + (image * torch.rand(image.shape, generator=g).to(image.dtype)).sum()
    return total


def render_and_grad(batched: bool, backend: str, dtype: torch.dtype, posed: bool = False) -> dict[str, torch.Tensor]:
    scenes, cameras = views(dtype, posed)
    background = torch.tensor([0.3, 0.6, 0.1], dtype=dtype, requires_grad=True)
    if batched:
        outputs = rasterize_batch(scenes, cameras, background, backend=backend)
    else:
        outputs = [rasterize(s, c, background, backend=backend) for s, c in zip(scenes, cameras, strict=True)]
    weighted_loss(outputs).backward()
    results = {"background.grad": background.grad}
    for v, (out, scene, camera) in enumerate(zip(outputs, scenes, cameras, strict=True)):
        results.update({f"{v}.color": out.color, f"{v}.depth": out.depth, f"{v}.alpha": out.alpha,
                        f"{v}.visible": out.visible, f"{v}.means2d": out.means2d,
                        f"{v}.means2d.grad": out.means2d.grad, f"{v}.viewmat.grad": camera.viewmat.grad})
        results.update({f"{v}.{k}.grad": getattr(scene, k).grad for k in PARAMS})
    return {k: v.detach() for k, v in results.items() if v is not None}


def test_cpu_batch_matches_the_reference_values_and_gradients() -> None:
    cpu = render_and_grad(True, "cpu", torch.float32)
    ref = render_and_grad(True, "torch", torch.float64)
    assert cpu.keys() == ref.keys()
    for v in range(len(VIEWS)):
        assert torch.equal(cpu[f"{v}.visible"], ref[f"{v}.visible"]), v
    errors = {k: relative_error(cpu[k], ref[k]) for k in ref if not k.endswith("visible")}
    assert max(errors.values()) < TOLERANCE, errors
    assert cpu["2.means.grad"].shape == (0, 3) and cpu["2.means2d.grad"].shape == (0, 2)


def test_cpu_batch_viewmat_gradients_match_the_reference() -> None:
    cpu = render_and_grad(True, "cpu", torch.float32, posed=True)
    ref = render_and_grad(True, "torch", torch.float64, posed=True)
    assert cpu.keys() == ref.keys()
    for v in range(len(VIEWS)):
        key = f"{v}.viewmat.grad"
        assert cpu[key].shape == (4, 4) and not cpu[key][3].any() and not ref[key][3].any(), key
        assert relative_error(cpu[key], ref[key]) < TOLERANCE, (key, relative_error(cpu[key], ref[key]))
    assert not cpu["2.viewmat.grad"].any()  # the view without Gaussians
    fixed = render_and_grad(True, "cpu", torch.float32)
    assert fixed.keys() == {k for k in cpu if not k.endswith("viewmat.grad")}
    for key, value in fixed.items():
        assert torch.equal(cpu[key], value), key


@pytest.mark.parametrize("posed", [False, True])
@pytest.mark.parametrize("backend", ["cpu", "torch"])
def test_a_batch_is_exactly_one_render_per_view(backend: str, posed: bool) -> None:
    batched = render_and_grad(True, backend, torch.float32, posed)
    alone = render_and_grad(False, backend, torch.float32, posed)
    assert batched.keys() == alone.keys()
    # The shared background's gradient sums the views' in another order (float64 in the batch).
    torch.testing.assert_close(batched.pop("background.grad"), alone.pop("background.grad"), rtol=1e-6, atol=0)
    for key, value in alone.items():
        assert torch.equal(batched[key], value), key


def test_a_batch_needs_one_camera_per_scene() -> None:
    scenes, cameras = views(torch.float32)
    with pytest.raises(ValueError, match="one camera per scene"):
        rasterize_batch(scenes, cameras[:2], backend="cpu")


@pytest.mark.parametrize("backend", ["cpu", "torch"])
def test_views_stacked_render_as_a_list_of_them_does(backend: str) -> None:
    """A static-shape decode stacks its views (V, N, ...): the same images and gradients as the views
    given one by one (the cpu backend takes the stack's rows as they are, the others unbind it)."""
    sizes = [(64, 48, 0.3), (64, 48, 0.075), (53, 37, 0.3)]
    stacked = {k: torch.stack([mixed_scene(seed, 300, 64, 48)[k] for seed in range(len(sizes))]) for k in PARAMS}
    cameras = [Camera(pose(seed), intrinsics(w, h), w, h, blur) for seed, (w, h, blur) in enumerate(sizes)]
    results = []
    for as_stack in (True, False):
        leaves = {k: v.clone().requires_grad_(True) for k, v in stacked.items()}
        scenes = (SplatSet(*(leaves[k] for k in PARAMS)) if as_stack else
                  [SplatSet(*(leaves[k][v] for k in PARAMS)) for v in range(len(sizes))])
        outputs = rasterize_batch(scenes, cameras, backend=backend)
        weighted_loss(outputs).backward()
        images = [image for out in outputs for image in (out.color, out.depth, out.alpha, out.visible)]
        results.append((images, [out.means2d.grad for out in outputs], [leaves[k].grad for k in PARAMS]))
    for got, expected in zip(*results, strict=True):
        for a, b in zip(got, expected, strict=True):
            assert torch.equal(a, b)
