"""Adam that steps only the rows a step saw (``optim.selective``; Taming 3DGS's selective Adam).

torch's Adam decays every row's moments and moves its value by the momentum left in them even where a
step gave the row no gradient, as the anchors out of every view of the step get none. Here the groups
named as row groups update only the rows ``select`` marks visible: those rows exactly as torch's Adam
would (its formulas, the parameter's step count for the bias corrections, as the hash grid's lazy Adam
uses the global count), the others keep value and moments. The other groups (the decoders, the
exposures) step through torch's Adam as before.

The update is elementwise over the whole buffer with the rows masked, so its shapes do not depend on
which rows were seen (nothing for the host to wait on), and a buffer's inert rows, never visible, stay
inert. gsplat's own ``SelectiveAdam`` kernel applies no bias correction, so it is not the same update.
"""

from __future__ import annotations

from collections.abc import Iterable

import torch


class SelectiveAdam(torch.optim.Adam):
    """``torch.optim.Adam`` whose groups named in ``row_groups`` (each parameter (rows, ...)) update only the
    rows marked by ``select`` before each ``step``; without a mark a step updates every row, as Adam."""

    def __init__(self, params: Iterable, row_groups: Iterable[str], **options) -> None:
        super().__init__(params, **options)
        self.row_groups = frozenset(row_groups)
        self.visible: torch.Tensor | None = None

    def select(self, visible: torch.Tensor) -> None:
        """Mark the rows (a (rows,) bool tensor) the next ``step`` updates in the row groups."""
        self.visible = visible

    @torch.no_grad()
    def step(self, closure=None):
        visible, self.visible = self.visible, None
        held = []
        if visible is not None:
            for group in self.param_groups:
                if group.get("name") in self.row_groups:
                    held += [(group, param, param.grad) for param in group["params"] if param.grad is not None]
        for _, param, _ in held:  # torch's step skips parameters without a gradient
            param.grad = None
        try:
            loss = super().step(closure)
        finally:
            for _, param, grad in held:
                param.grad = grad
        for group, param, grad in held:
            self._update_rows(group, param, grad, visible)
        return loss

    def _update_rows(self, group: dict, param: torch.Tensor, grad: torch.Tensor, visible: torch.Tensor) -> None:
        """torch's single-tensor Adam (no weight decay, amsgrad or maximize) on the rows of ``visible``."""
        state = self.state[param]
        if not state:  # as torch's Adam starts a parameter's state
            on_device = group["fused"] or group["capturable"]
            state["step"] = torch.zeros((), dtype=torch.float32, device=param.device if on_device else None)
            state["exp_avg"] = torch.zeros_like(param, memory_format=torch.preserve_format)
            state["exp_avg_sq"] = torch.zeros_like(param, memory_format=torch.preserve_format)
        exp_avg, exp_avg_sq, step = state["exp_avg"], state["exp_avg_sq"], state["step"]
        beta1, beta2 = group["betas"]
        step += 1
        first = exp_avg.lerp(grad, 1 - beta1)
        second = exp_avg_sq.mul(beta2).addcmul_(grad, grad, value=1 - beta2)
        value = moved(param, first, second, step, group, host=step.device.type == "cpu")
        rows = visible.view(-1, *([1] * (param.dim() - 1)))
        exp_avg.copy_(torch.where(rows, first, exp_avg))
        exp_avg_sq.copy_(torch.where(rows, second, exp_avg_sq))
        param.copy_(torch.where(rows, value, param))


def moved(param: torch.Tensor, first: torch.Tensor, second: torch.Tensor, step: torch.Tensor, group: dict, *,
          host: bool) -> torch.Tensor:
    """``param`` after Adam's step with the updated moments ``first`` and ``second`` at step count ``step``, by
    torch's own formulas: ``host`` reads the count (its branch for a count on the host), else the bias
    corrections stay tensors (its ``capturable`` branch, for a count on the device the host never reads)."""
    beta1, beta2 = group["betas"]
    lr, eps = group["lr"], group["eps"]
    if host:
        count = step.item()
        denominator = (second.sqrt() / (1 - beta2**count) ** 0.5).add_(eps)
        return param.addcdiv(first, denominator, value=-lr / (1 - beta1**count))
    step_size_neg = (lr / (1 - beta1**step)).neg()
    denominator = (second.sqrt() / ((1 - beta2**step).sqrt() * step_size_neg)).add_(eps / step_size_neg)
    return param.addcdiv(first, denominator)
