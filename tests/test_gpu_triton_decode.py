"""The compiled Triton fused decode on a GPU, at full size: against the reference, in a compiled graph, and timed.

The reference is the torch decode (``static_gaussians.generate_drawn``) in float64, so neither side's rounding
decides the comparison; the kernels run in float32 and match it within 1e-4 of each value's and each
gradient's largest magnitude. Rows with an opacity logit within 1e-3 of zero in a view are left out of that
view, so that no Gaussian is drawn on one side and not on the other. The timing (the window's decode forward
and backward, through the kernels and through the float32 torch decode, CUDA events, median of 20) goes to
the terminal and to ``$OGMAP_GPU_REPORT/triton-decode.json`` (``bench/gpu/check.sh`` sets it): reported,
not asserted.
"""

from __future__ import annotations

import copy
import json
import os
from collections.abc import Callable
from pathlib import Path

import pytest
import torch
from test_triton_decode import OUTPUTS, Window, assert_close, decoded, window
from torch import nn
from triton_kernels import DECODE, HAS_TRITON, NO_TRITON, kernels, median_ms

from ogmapping.model.gaussians import decoded_logits
from ogmapping.model.static_gaussians import generate_drawn

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device"),
              pytest.mark.skipif(not HAS_TRITON, reason=NO_TRITON)]
# a 640x480 sparse map's buffers and window (n = 5), and Scaffold-GS's ten offsets with a larger hidden layer
SIZES = [dict(count=50_000, capacity=65_536, n=5, features=32, hidden=32, views=8, with_colours=True),
         dict(count=20_000, capacity=32_768, n=10, features=32, hidden=64, views=3, with_colours=False)]
NAMES = ["n5-window8", "n10-hidden64"]


def _cuda() -> torch.device:
    _, device = kernels(DECODE)
    if device.type != "cuda":
        pytest.skip("TRITON_INTERPRET=1 is set in this pytest process: run the GPU tests on their own (pytest -m gpu)")
    return device


def in_double(case: Window) -> Window:
    """The same window in float64: its rows, decoders and cameras."""
    anchors = copy.copy(case.anchors)
    anchors.learnable = {name: nn.Parameter(row.detach().double()) for name, row in case.anchors.learnable.items()}
    anchors.rows = {**case.anchors.rows, "positions": case.anchors.rows["positions"].double()}
    return Window(anchors, copy.deepcopy(case.decoders).double(), case.centers.double(), case.in_view)


def without_near_zero_logits(case: Window) -> None:
    """Leave out of each view the rows with an opacity logit within 1e-3 of zero (float64), in place."""
    double = in_double(case)
    features, positions = double.anchors.parameter("features"), double.anchors.buffer("positions")
    with torch.no_grad():
        for view, center in enumerate(double.centers):
            opacity, _, _ = decoded_logits(double.decoders, features, positions, center)
            case.in_view[view] &= (opacity.abs() >= 1e-3).all(dim=1)


@pytest.mark.parametrize("size", SIZES, ids=NAMES)
def test_the_kernels_match_the_float64_decode_at_full_size(size: dict) -> None:
    case = window(_cuda(), **size)
    without_near_zero_logits(case)
    actual, grads = decoded(case, fused=True)
    expected, expected_grads = decoded(in_double(case), fused=False)
    assert actual.drawn.any() and torch.equal(actual.drawn, expected.drawn)
    for name in (*OUTPUTS, "anchor_opacity"):
        assert_close(getattr(actual, name), getattr(expected, name), name)
    assert grads.keys() == expected_grads.keys()
    for name, grad in expected_grads.items():
        assert_close(grads[name], grad, f"gradient of {name}")


def test_the_compiled_step_graph_traces_the_kernels() -> None:
    """``generate_drawn`` compiled whole (as ``ogmapping.mapping.graphs`` compiles the decode) equals it eager."""
    case = window(_cuda(), count=3000, capacity=4096, n=5, features=32, hidden=32, views=4, with_colours=True)
    compiled = torch.compile(generate_drawn, fullgraph=True)
    results = []
    for run in (generate_drawn, compiled):
        outputs = run(case.anchors, case.anchors.parameter("features"), case.decoders, case.centers, case.in_view,
                      fused=True)
        parameters = [*case.anchors.learnable.values(), *case.decoders.parameters()]
        total = sum(getattr(outputs, name).sum() * (index + 1) for index, name in enumerate(OUTPUTS))
        results.append((*(getattr(outputs, name).detach() for name in OUTPUTS),
                        *torch.autograd.grad(total, parameters)))
    for eager, traced in zip(*results, strict=True):
        assert_close(traced, eager, "compiled against eager")


def _forward_backward(case: Window, fused: bool) -> Callable[[], None]:
    """The window's decode and the gradients of a fixed weighing of its values, all on the device."""
    parameters = [*case.anchors.learnable.values(), *case.decoders.parameters()]

    def decode():
        return generate_drawn(case.anchors, case.anchors.parameter("features"), case.decoders, case.centers,
                              case.in_view, fused=fused)

    with torch.no_grad():
        weights = {name: torch.randn_like(getattr(decode(), name)) for name in OUTPUTS}

    def step() -> None:
        drawn = decode()
        torch.autograd.grad(sum((getattr(drawn, name) * weights[name]).sum() for name in OUTPUTS), parameters,
                            allow_unused=True)

    return step


def test_the_decode_is_timed_against_the_torch_decode() -> None:
    report = {"gpu": torch.cuda.get_device_name(_cuda()), "torch": torch.__version__}
    for size, name in zip(SIZES, NAMES, strict=True):
        case = window(torch.device("cuda"), **size)
        figures = {f"{label}_ms": median_ms(_forward_backward(case, fused))
                   for label, fused in (("triton", True), ("torch", False))}
        report[name] = {**size, **figures}
        print(f"\ndecode forward+backward, {name} on {report['gpu']}: Triton {figures['triton_ms']:.3f} ms, "
              f"torch {figures['torch_ms']:.3f} ms")
    folder = os.environ.get("OGMAP_GPU_REPORT")
    if folder:
        Path(folder).mkdir(parents=True, exist_ok=True)
        (Path(folder) / "triton-decode.json").write_text(json.dumps(report, indent=2) + "\n")
