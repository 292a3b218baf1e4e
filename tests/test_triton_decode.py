"""The Triton fused decode equals the torch decode of ``static_gaussians.generate_drawn``, values and the
gradients of every row table and decoder weight (interpreted on the CPU; compiled where there is a GPU)."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from triton_kernels import DECODE, HAS_TRITON, NO_TRITON, kernels

import ogmapping.mapper
from ogmapping.config import resolve
from ogmapping.datasets.synthetic import SyntheticSource
from ogmapping.model import static_gaussians
from ogmapping.model.decoders import Decoders
from ogmapping.model.static_gaussians import DrawnWindow, generate_drawn
from ogmapping.structure.anchors import LEARNABLE, AnchorMap

pytestmark = pytest.mark.skipif(not HAS_TRITON, reason=NO_TRITON)
OUTPUTS = ("means", "quats", "scales", "opacities", "colors")


@dataclasses.dataclass
class Window:
    anchors: AnchorMap
    decoders: Decoders
    centers: torch.Tensor  # (V, 3)
    in_view: torch.Tensor  # (V, capacity): live rows drawn at random


def window(device: torch.device, *, count: int, capacity: int, n: int, features: int, hidden: int, views: int,
           with_colours: bool, seed: int = 0) -> Window:
    """``count`` live anchors in buffers of ``capacity`` rows, random offsets, scales, features and colours,
    decoders of their random start, and ``views`` cameras around them."""
    generator = torch.Generator().manual_seed(seed)
    anchors = AnchorMap(n, features, True, device, with_colours=with_colours, capacity=capacity)

    def normal(*shape: int) -> torch.Tensor:
        return torch.randn(*shape, generator=generator).to(device)

    anchors.add(torch.arange(count, device=device), torch.zeros(count, dtype=torch.int64, device=device),
                normal(count, 3), torch.full((count,), 0.05, device=device), normal(count, features), None,
                normal(count, 3) if with_colours else None)
    with torch.no_grad():
        anchors.offsets.copy_(normal(count, n, 3))
        anchors.log_scales.copy_(normal(count, 3) * 0.3 - 3.0)
    decoders = Decoders(features, n, hidden, generator).to(device)
    in_view = (torch.rand(views, capacity, generator=generator) < 0.8).to(device) & anchors.live
    return Window(anchors, decoders, normal(views, 3) * 2.0, in_view)


def decoded(case: Window, fused: bool, only: tuple[str, ...] = OUTPUTS) -> tuple[DrawnWindow, dict[str, torch.Tensor]]:
    """The window decoded, and every gradient of a loss weighing each value of ``only`` at random."""
    named = [*((name, case.anchors.parameter(name)) for name in LEARNABLE), *case.decoders.named_parameters()]
    for _, parameter in named:
        parameter.grad = None
    drawn = generate_drawn(case.anchors, case.anchors.parameter("features"), case.decoders, case.centers,
                           case.in_view, fused=fused)
    generator = torch.Generator().manual_seed(1)
    loss = sum((getattr(drawn, name) * torch.randn(getattr(drawn, name).shape, generator=generator).to(
        case.centers.device)).sum() for name in only)
    if loss.requires_grad:
        loss.backward()
    return drawn, {name: parameter.grad for name, parameter in named if parameter.grad is not None}


def assert_close(mine: torch.Tensor, theirs: torch.Tensor, what: str) -> None:
    mine, theirs = mine.detach().cpu(), theirs.detach().cpu()
    assert mine.shape == theirs.shape, what
    if theirs.numel():
        error = float((mine - theirs).abs().max()) / max(float(theirs.abs().max()), 1e-12)
        assert error <= 1e-4, f"{what}: off by {error:.2e} of its largest value"


def assert_matches(case: Window, only: tuple[str, ...] = OUTPUTS) -> tuple[DrawnWindow, dict[str, torch.Tensor]]:
    """The fused decode's values and gradients (which it returns) against the torch decode's."""
    expected, expected_grads = decoded(case, fused=False, only=only)
    actual, grads = decoded(case, fused=True, only=only)
    for name in (*OUTPUTS, "anchor_opacity"):
        assert_close(getattr(actual, name), getattr(expected, name), name)
    for name in ("drawn", "in_view", "rows", "slots", "anchor_rows"):
        assert torch.equal(getattr(actual, name), getattr(expected, name)), name
    # one operator: every input the loss does not reach gets a zero gradient, where autograd's gets none
    assert grads.keys() >= expected_grads.keys()
    for name, grad in grads.items():
        assert_close(grad, expected_grads.get(name, torch.zeros_like(grad)), f"gradient of {name}")
    return actual, grads


@pytest.mark.parametrize(("count", "capacity", "n", "features", "hidden", "views", "with_colours"), [
    (40, 50, 5, 8, 12, 3, True),  # blocks of rows with padded rows past the count, three views
    (70, 70, 3, 5, 20, 1, False),  # a partial last block, one view, widths that are no power of two
])
def test_values_and_gradients_match_the_torch_decode(count, capacity, n, features, hidden, views, with_colours):
    _, device = kernels(DECODE)
    case = window(device, count=count, capacity=capacity, n=n, features=features, hidden=hidden, views=views,
                  with_colours=with_colours)
    _, grads = assert_matches(case)
    expected = {*LEARNABLE, *(name for name, _ in case.decoders.named_parameters())}
    assert grads.keys() == expected - (set() if with_colours else {"colours"})


def test_a_single_gaussian() -> None:
    _, device = kernels(DECODE)
    assert_matches(window(device, count=1, capacity=1, n=1, features=4, hidden=3, views=1, with_colours=True))


def test_an_empty_window() -> None:
    """No anchor rows at all: empty outputs, zero weight gradients; and rows none of which is in view."""
    _, device = kernels(DECODE)
    empty = window(device, count=0, capacity=0, n=2, features=4, hidden=8, views=2, with_colours=True)
    drawn, grads = assert_matches(empty)
    assert drawn.means.shape == (2, 0, 3) and drawn.anchor_opacity.shape == (2, 0)
    assert not any(grad.any() for grad in grads.values())
    unseen = window(device, count=20, capacity=20, n=2, features=4, hidden=8, views=2, with_colours=False)
    unseen.in_view.zero_()
    drawn, grads = assert_matches(unseen)
    assert not drawn.drawn.any() and not drawn.opacities.any()
    assert not any(grads[name].any() for name in ("opacity.0.weight", "opacity.0.bias", "opacity.2.weight"))


def test_padded_rows_stay_inert() -> None:
    """Rows past the count are never drawn: opacity 0, and a loss on the opacities gives them no gradient."""
    _, device = kernels(DECODE)
    case = window(device, count=30, capacity=48, n=4, features=6, hidden=16, views=2, with_colours=True)
    drawn, grads = assert_matches(case, only=("opacities",))
    padded = drawn.rows >= 30
    assert drawn.drawn.any() and not drawn.drawn[:, padded].any() and not drawn.opacities[:, padded].any()
    for name in LEARNABLE:
        assert not grads[name][30:].any(), name


def test_programs_that_take_several_blocks(monkeypatch) -> None:
    """More blocks of rows than backward programs: each program sums its blocks' weight gradients."""
    module, device = kernels(DECODE)
    monkeypatch.setattr(module, "MAX_PROGRAMS", 2)
    assert_matches(window(device, count=75, capacity=80, n=2, features=3, hidden=8, views=2, with_colours=True))


def test_the_gradients_are_the_same_bits_every_run() -> None:
    _, device = kernels(DECODE)
    case = window(device, count=40, capacity=40, n=3, features=4, hidden=8, views=2, with_colours=True)
    _, first = decoded(case, fused=True)
    _, second = decoded(case, fused=True)
    for name, grad in first.items():
        assert torch.equal(grad, second[name]), name


def test_inputs_it_cannot_take_are_refused() -> None:
    module, device = kernels(DECODE)
    case = window(device, count=4, capacity=4, n=2, features=3, hidden=4, views=1, with_colours=False)
    anchors = case.anchors
    rows = [anchors.parameter("features"), anchors.buffer("positions"), anchors.parameter("offsets"),
            anchors.parameter("log_scales"), None, case.centers, case.in_view, case.decoders]
    with pytest.raises(ValueError, match="runs in float32"):
        module.decode_window(rows[0].double(), *rows[1:])
    with pytest.raises(ValueError, match="bool in-view mask"):
        module.decode_window(*rows[:6], case.in_view.float(), case.decoders)
    with pytest.raises(ValueError, match="in-view mask of"):
        module.decode_window(*rows[:6], case.in_view[:, :3], case.decoders)
    with pytest.raises(ValueError, match="no gradient to the anchor or camera centres"):
        module.decode_window(*rows[:5], case.centers.clone().requires_grad_(), *rows[6:])


def test_a_static_step_with_the_profile_flag_asks_for_the_kernels(monkeypatch) -> None:
    """With ``profile.triton_decode`` a static-shape step asks ``generate_drawn`` for the fused decode (the
    torch decode stands in for the kernels here: the step's wiring is what is checked)."""
    asked = []

    def recorded(*args, fused: bool):
        asked.append(fused)
        return generate_drawn(*args, fused=False)

    monkeypatch.setattr(static_gaussians, "generate_drawn", recorded)
    chosen = ogmapping.mapper.execution_profile
    monkeypatch.setattr(ogmapping.mapper, "execution_profile",
                        lambda *args: dataclasses.replace(chosen(*args), triton_decode=True))
    source = SyntheticSource(n_frames=1, width=32, height=24)
    config = resolve("sparse", overrides={"keyframes.first_iterations": 2, "step": "static"})
    ogmapping.mapper.Mapper(config, "cpu").process(source[0])
    assert asked == [True, True]
