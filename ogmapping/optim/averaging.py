"""The map that renders: an exponential moving average of the learnable values over the last steps.

An online map follows whichever views it trained on last (bench/RESULTS.md, "Map averaging"); the
average of its values over the last few steps (Polyak averaging) renders every view better. Training
keeps stepping the live values; queries (renders, snapshots, exports) use the average. The average
is debiased per row, so an anchor grown a few steps ago averages only its own steps, not the zeros
before it: after k updates with decay d the newest value weighs (1 - d) / (1 - d^k), so the first
update copies the value.

What is averaged: the anchors' rows (kept in ``AnchorMap``, which carries them through growth and
pruning) and the decoders. The dense version's hash table is not: it is stepped lazily, row by row,
and averaging all of it would cost a pass over the whole table per step.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

import torch
from torch import nn

from ogmapping.structure.anchors import LEARNABLE, AnchorMap

DECODER_PREFIX = "decoders."


def newest_weight(steps: torch.Tensor, decay: float) -> torch.Tensor:
    """Weight of the newest value in a debiased average after ``steps`` (>= 1) updates."""
    return (1.0 - decay) / (1.0 - torch.pow(decay, steps.to(torch.float64))).to(torch.float32)


def _blend(average: torch.Tensor, value: torch.Tensor, weight: torch.Tensor) -> None:
    average.add_((value - average) * weight.view(-1, *([1] * (value.dim() - 1))))


@torch.no_grad()
def fold_in(anchors: AnchorMap, decoders: nn.Module, decoder_values: dict[str, torch.Tensor],
            decoder_steps: torch.Tensor, decay: float) -> None:
    """One update of the average with ``decay``: every row of the anchor buffers (their shapes stay put)
    and every decoder value, each row debiased by its own count, the decoders by their shared one."""
    steps = anchors.buffer("average_steps")
    steps += 1
    weight = newest_weight(steps, decay)
    for name in LEARNABLE:
        _blend(anchors.average_rows[name], anchors.parameter(name), weight)
    decoder_steps += 1
    weight = newest_weight(decoder_steps, decay)
    for name, value in decoders.named_parameters():
        _blend(decoder_values[name], value, weight)


class MapAverage:
    """The moving average of one mapper's anchors and decoders (``decay`` 0: off, queries see the live map)."""

    def __init__(self, anchors: AnchorMap, decoders: nn.Module, decay: float, growth: float = 0.0) -> None:
        self.anchors = anchors
        self.decoders = decoders
        self.decay = decay
        self.growth = growth
        self.decoder_values = {name: torch.zeros_like(value) for name, value in decoders.named_parameters()}
        self.decoder_steps = 0
        # The same count on the map's device, stepped there: a new tensor per step would be a host-to-device copy.
        self._decoder_steps = torch.zeros(1, dtype=torch.int64, device=anchors.device)

    @property
    def enabled(self) -> bool:
        return self.decay > 0.0

    def decay_at(self, step: int) -> float:
        """The decay of the map's ``step``-th update: ``decay``, until ``growth`` times the map's steps
        exceeds its horizon of 1 / (1 - decay) steps; from then on the horizon is that many steps.

        A young map is still converging and an average lagging it loses (Replica room0, 94-114 steps),
        while an old one gains from a longer average (7-Scenes, 700-1000 steps; bench/RESULTS.md).
        """
        if self.growth <= 0.0:
            return self.decay
        return max(self.decay, 1.0 - 1.0 / (self.growth * step))

    def update(self, fold: Callable = fold_in) -> None:
        """Fold the live values in, after an optimiser step; ``fold`` is ``fold_in`` or its compiled graph."""
        if not self.enabled:
            return
        decay = self.decay_at(self.decoder_steps + 1)
        fold(self.anchors, self.decoders, self.decoder_values, self._decoder_steps, decay)
        self.decoder_steps += 1

    def _averaged_values(self) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """(live parameter, its average) pairs; rows never averaged keep their live value."""
        anchors = self.anchors
        pairs = []
        for name in LEARNABLE:
            live = getattr(anchors, name)
            seen = (anchors.average_steps > 0).view(-1, *([1] * (live.dim() - 1)))
            pairs.append((live, torch.where(seen, anchors.averages[name], live.detach())))
        if self.decoder_steps:
            pairs.extend((value, self.decoder_values[name]) for name, value in self.decoders.named_parameters())
        return pairs

    @contextmanager
    def applied(self) -> Iterator[None]:
        """The averaged values in place of the live ones while the block runs (hold the mapper's lock)."""
        if not self.enabled:
            yield
            return
        with torch.no_grad():
            swaps = [(param, param.detach().clone(), average) for param, average in self._averaged_values()]
            for param, _, average in swaps:
                param.copy_(average)
        try:
            yield
        finally:
            with torch.no_grad():
                for param, live, _ in swaps:
                    param.copy_(live)

    def state(self) -> dict[str, torch.Tensor]:
        """The decoders' averages and step count (the anchors' rows travel with the anchors)."""
        tensors = {DECODER_PREFIX + name: value for name, value in self.decoder_values.items()}
        tensors["decoder_steps"] = torch.tensor([self.decoder_steps], dtype=torch.int64)
        return tensors

    def load(self, tensors: dict[str, torch.Tensor]) -> None:
        """Restore what ``state`` captured; ValueError when a shape does not fit the decoders."""
        for name, value in self.decoder_values.items():
            restored = tensors[DECODER_PREFIX + name]
            if restored.shape != value.shape:
                raise ValueError(f"average {DECODER_PREFIX}{name}: shape {tuple(restored.shape)}, "
                                 f"expected {tuple(value.shape)}")
            value.copy_(restored)
        self.decoder_steps = int(tensors["decoder_steps"][0])
        self._decoder_steps.fill_(self.decoder_steps)
