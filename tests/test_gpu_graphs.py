"""Probe for CUDA graphs around a step's static part: the decoders, captured once, replayed.

A step's decoder pass is three small MLPs over the anchors a window sees, a handful of kernels
each forward and backward; launch overhead, not arithmetic, is what it costs on a GPU. A CUDA graph
replays them with one launch, but needs static shapes, and the anchors in view change every step,
so a graph would run on rows padded up to a bucket (a multiple of ``BUCKET``). This measures that
before any code path adopts it:

- the graphed decoders (``torch.cuda.make_graphed_callables``) on padded rows give the eager
  decoders' outputs and parameter gradients on the real rows (padding rows carry zero gradient);
- forward + backward of both, timed with CUDA events: reported on the terminal and in
  ``$OGMAP_GPU_REPORT/decoder-graphs.json`` (``bench/gpu/check.sh`` sets it), not asserted.
"""

from __future__ import annotations

import json
import os
import statistics
from pathlib import Path

import pytest
import torch

from ogmapping.config import resolve
from ogmapping.model.decoders import Decoders

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")]
BUCKET = 2048
ROWS = 5000  # about the anchors a `sparse` window of four views sees on 7-Scenes at 640x480
REPEATS = 50


def decoders_and_rows(rows: int) -> tuple[Decoders, torch.Tensor]:
    model = resolve("sparse").model
    generator = torch.Generator().manual_seed(0)
    decoders = Decoders(model.feature_dim, model.n_offsets, model.hidden_dim, generator).cuda()
    inputs = torch.randn(rows, model.feature_dim + 4, generator=generator).cuda()
    return decoders, inputs


def loss_of(outputs: tuple[torch.Tensor, ...], weights: tuple[torch.Tensor, ...]) -> torch.Tensor:
    return sum((output * weight).sum() for output, weight in zip(outputs, weights, strict=True))


class Stacked(torch.nn.Module):
    """The three decoders as one callable of the concatenated inputs (what ``Decoders.logits`` runs)."""

    def __init__(self, decoders: Decoders) -> None:
        super().__init__()
        self.decoders = decoders

    def forward(self, inputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return self.decoders.opacity(inputs), self.decoders.color(inputs), self.decoders.cov(inputs)


def test_graphed_decoders_match_eager_and_their_time_is_reported(capsys) -> None:
    decoders, inputs = decoders_and_rows(ROWS)
    padded_rows = -(-ROWS // BUCKET) * BUCKET
    eager = Stacked(decoders)
    padded = torch.zeros(padded_rows, inputs.shape[1], device="cuda")
    padded[:ROWS] = inputs
    graphed = torch.cuda.make_graphed_callables(Stacked(decoders), (padded.clone().requires_grad_(False),))
    g = torch.Generator(device="cuda").manual_seed(1)
    weights = tuple(torch.randn(ROWS, width, device="cuda", generator=g) for width in
                    (decoders.n, 3 * decoders.n, 7 * decoders.n))

    def step(module, rows_in) -> dict[str, torch.Tensor]:
        decoders.zero_grad(set_to_none=True)
        outputs = tuple(output[:ROWS] for output in module(rows_in))
        loss_of(outputs, weights).backward()
        return {"out": torch.cat([o.detach().reshape(-1) for o in outputs]),
                **{name: p.grad.clone() for name, p in decoders.named_parameters()}}

    expected, actual = step(eager, inputs), step(graphed, padded)
    for name, value in expected.items():
        torch.testing.assert_close(actual[name], value, rtol=1e-4, atol=1e-5, msg=name)

    timings = {}
    for label, module, rows_in in (("eager", eager, inputs), ("graphed", graphed, padded)):
        times = []
        for _ in range(REPEATS):
            begin, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            begin.record()
            step(module, rows_in)
            end.record()
            end.synchronize()
            times.append(begin.elapsed_time(end))
        timings[label] = statistics.median(times[5:])
    summary = {"rows": ROWS, "padded_rows": padded_rows, "forward_backward_ms": timings,
               "device": torch.cuda.get_device_name()}
    folder = os.environ.get("OGMAP_GPU_REPORT")
    if folder:
        Path(folder).mkdir(parents=True, exist_ok=True)
        (Path(folder) / "decoder-graphs.json").write_text(json.dumps(summary, indent=2))
    with capsys.disabled():
        print(f"\ndecoders forward+backward over {ROWS} rows: eager {timings['eager']:.3f} ms, "
              f"graphed on {padded_rows} padded rows {timings['graphed']:.3f} ms ({summary['device']})")
