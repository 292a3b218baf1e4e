"""Image and depth quality metrics: PSNR, SSIM, depth L1 (cm) and, where it can run offline, LPIPS.

SSIM follows the protocol of the reference numbers in ``shared/data/7scenes-redkitchen/SOURCE.md``
(11x11 Gaussian window, sigma 1.5, 5-pixel border dropped) and reuses the loss's implementation,
so the figure reported is the figure optimised. LPIPS never downloads anything: it runs only when
the ``lpips`` package and torchvision's AlexNet weights are already on disk.
"""

from __future__ import annotations

import importlib
import importlib.util
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ogmapping.ssim import WINDOW_SIZE, ssim_map

SSIM_BORDER = WINDOW_SIZE // 2
METRIC_KEYS = ("psnr", "ssim", "depth_l1_cm", "lpips")
# torchvision's AlexNet (IMAGENET1K_V1) checkpoint, as torch.hub names it in its cache.
ALEXNET_CHECKPOINT = "alexnet-owt-7be5be79.pth"

ArrayLike = np.ndarray | torch.Tensor


def _tensor(x: ArrayLike) -> torch.Tensor:
    """Float64 tensor on the input's device (numpy arrays land on the CPU)."""
    t = torch.from_numpy(np.asarray(x)) if isinstance(x, np.ndarray) else x.detach()
    return t.to(torch.float64)


def psnr(pred: ArrayLike, gt: ArrayLike) -> float:
    """Peak signal-to-noise ratio in dB for images in [0, 1]; inf for identical images."""
    mse = float(((_tensor(pred) - _tensor(gt)) ** 2).mean())
    return math.inf if mse == 0.0 else -10.0 * math.log10(mse)


def ssim(pred: ArrayLike, gt: ArrayLike) -> float:
    """Mean SSIM of two (H, W, 3) images in [0, 1], with a border of half a window dropped."""
    a, b = _tensor(pred), _tensor(gt)
    if min(a.shape[0], a.shape[1]) <= 2 * SSIM_BORDER:
        raise ValueError(f"ssim needs images larger than {2 * SSIM_BORDER} pixels a side, got {a.shape}")
    full = ssim_map(a, b)
    return float(full[SSIM_BORDER:-SSIM_BORDER, SSIM_BORDER:-SSIM_BORDER].mean())


def depth_l1_cm(pred_depth: ArrayLike, gt_depth: ArrayLike) -> float:
    """Mean |pred - gt| in centimetres over valid measurements (gt > 0, finite); NaN if none."""
    pred, gt = _tensor(pred_depth), _tensor(gt_depth)
    valid = (gt > 0) & torch.isfinite(gt)
    if not bool(valid.any()):
        return math.nan
    return float((pred[valid] - gt[valid]).abs().mean()) * 100.0


def _alexnet_checkpoint() -> Path:
    return Path(torch.hub.get_dir()) / "checkpoints" / ALEXNET_CHECKPOINT


def lpips_status() -> tuple[bool, str]:
    """Whether LPIPS (AlexNet) can run here without a download, and why not if it cannot."""
    for package in ("lpips", "torchvision"):
        if importlib.util.find_spec(package) is None:
            return False, f"the {package!r} package is not installed"
    try:
        lpips = importlib.import_module("lpips")
    except Exception as error:  # a broken install must not stop the evaluation
        return False, f"importing lpips failed: {error}"
    linear = Path(lpips.__file__).parent / "weights" / "v0.1" / "alex.pth"
    if not linear.is_file():
        return False, f"lpips' own linear-layer weights are missing ({linear})"
    checkpoint = _alexnet_checkpoint()
    if not checkpoint.is_file():
        return False, f"torchvision's AlexNet weights are not in the torch hub cache ({checkpoint})"
    return True, "ok"


class Lpips:
    """LPIPS (AlexNet, v0.1) built from local files only; scores are None when it is unavailable."""

    def __init__(self, device: torch.device | str = "cpu") -> None:
        self.available, self.reason = lpips_status()
        self.model: Any = None
        if self.available:
            self.model = self._build().to(device)

    @staticmethod
    def _build() -> Any:
        """LPIPS with a randomly initialised backbone (so nothing is fetched), then the cached weights."""
        lpips = importlib.import_module("lpips")
        model = lpips.LPIPS(net="alex", version="0.1", pnet_rand=True, verbose=False)
        state = torch.load(_alexnet_checkpoint(), map_location="cpu", weights_only=True)
        loaded = 0
        for block in model.net.children():  # slices holding torchvision's ``features[i]`` as child "i"
            for index, layer in block.named_children():
                for name, param in layer.named_parameters(recurse=False):
                    param.data.copy_(state[f"features.{index}.{name}"])
                    loaded += 1
        expected = sum(1 for key in state if key.startswith("features."))
        if loaded != expected:
            raise RuntimeError(f"loaded {loaded} of {expected} AlexNet feature tensors into LPIPS")
        return model.eval()

    @torch.no_grad()
    def __call__(self, pred: ArrayLike, gt: ArrayLike) -> float | None:
        """LPIPS distance of two (H, W, 3) images in [0, 1], or None when unavailable."""
        if self.model is None:
            return None
        device = next(self.model.parameters()).device
        a = _tensor(pred).float().permute(2, 0, 1)[None].to(device)
        b = _tensor(gt).float().permute(2, 0, 1)[None].to(device)
        return float(self.model(a, b, normalize=True).mean())


def _mean(values: list[Any]) -> float | None:
    kept = [float(v) for v in values if v is not None and not math.isnan(float(v))]
    return sum(kept) / len(kept) if kept else None


def summarise(per_frame: list[dict[str, Any]]) -> dict[str, Any]:
    """Average each metric over the frames that have it (None/NaN skipped), plus the frame count."""
    summary: dict[str, Any] = {key: _mean([frame.get(key) for frame in per_frame]) for key in METRIC_KEYS}
    summary["frames"] = len(per_frame)
    return summary
