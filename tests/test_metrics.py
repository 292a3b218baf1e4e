"""Metrics against hand computations and an independent, direct SSIM."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from ogmapping.quality import metrics


def _direct_ssim(a: np.ndarray, b: np.ndarray) -> float:
    """SSIM by brute force: every 11x11 window fully inside the image, weights from the 2-D Gaussian."""
    r = 5
    offsets = np.arange(-r, r + 1)
    g = np.exp(-(offsets[:, None] ** 2 + offsets[None, :] ** 2) / (2 * 1.5**2))
    g /= g.sum()
    c1, c2 = 0.01**2, 0.03**2
    values = []
    for ch in range(a.shape[2]):
        for i in range(r, a.shape[0] - r):
            for j in range(r, a.shape[1] - r):
                x = a[i - r : i + r + 1, j - r : j + r + 1, ch]
                y = b[i - r : i + r + 1, j - r : j + r + 1, ch]
                mx, my = (g * x).sum(), (g * y).sum()
                vx, vy = (g * (x - mx) ** 2).sum(), (g * (y - my) ** 2).sum()
                cov = (g * (x - mx) * (y - my)).sum()
                values.append(((2 * mx * my + c1) * (2 * cov + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2)))
    return float(np.mean(values))


def test_psnr_matches_hand_computation():
    gt = np.zeros((4, 4, 3))
    pred = gt.copy()
    pred[0, 0, 0] = 0.5  # mse = 0.25 / 48
    assert metrics.psnr(pred, gt) == pytest.approx(10 * math.log10(48 / 0.25))
    assert metrics.psnr(torch.from_numpy(pred), torch.from_numpy(gt)) == pytest.approx(22.833, abs=1e-3)
    assert metrics.psnr(gt, gt) == math.inf


def test_psnr_affine_fits_the_frames_own_gain_and_offset():
    rng = np.random.default_rng(3)
    render = rng.random((12, 9, 3)) * 0.8 + 0.1
    assert metrics.psnr_affine(render, render) == metrics.psnr(render, render) == math.inf
    darker = 0.6 * render + 0.05  # a known affine: recovered exactly
    scale, shift = metrics.affine_fit(render, darker)
    assert scale == pytest.approx(0.6, abs=1e-12) and shift == pytest.approx(0.05, abs=1e-12)
    assert metrics.psnr_affine(render, darker) > 200 > metrics.psnr(render, darker)
    noisy = np.clip(darker + rng.normal(0, 0.02, render.shape), 0, 1)  # and with noise, never below the raw PSNR
    assert metrics.psnr(render, noisy) < metrics.psnr_affine(render, noisy) < metrics.psnr(darker, noisy) + 0.5
    flat = np.full_like(render, 0.3)  # a constant render: the offset alone, to the truth's mean
    assert metrics.affine_fit(flat, render) == pytest.approx((1.0, float(render.mean()) - 0.3))
    clipped = np.clip(1.5 * render, 0, 1)  # the fit clips to [0, 1] as images are
    assert metrics.psnr_affine(render, clipped) >= metrics.psnr(render, clipped)


def test_ssim_identical_is_one_and_matches_direct_computation():
    rng = np.random.default_rng(0)
    a = rng.random((20, 23, 3))
    b = np.clip(a + rng.normal(0, 0.1, a.shape), 0, 1)
    assert metrics.ssim(a, a) == pytest.approx(1.0)
    assert metrics.ssim(a, b) == pytest.approx(_direct_ssim(a, b), abs=1e-10)
    assert metrics.ssim(torch.from_numpy(a).float(), torch.from_numpy(b).float()) == pytest.approx(
        _direct_ssim(a, b), abs=1e-5
    )


def _direct_ms_ssim(a: np.ndarray, b: np.ndarray) -> float:
    """MS-SSIM from its definition (Wang et al. 2003): per channel, the contrast-structure term of each of
    five scales (2x2 means between them) and the luminance of the last, weighted; then the channels' mean.
    Sides that halve evenly down to the last scale, so no padding rule enters."""
    offsets = np.arange(-5, 6)
    g = np.exp(-(offsets**2) / (2 * 1.5**2))
    g /= g.sum()

    def blur(x: np.ndarray) -> np.ndarray:  # separable valid convolution
        rows = np.lib.stride_tricks.sliding_window_view(x, 11, axis=0) @ g
        return np.lib.stride_tricks.sliding_window_view(rows, 11, axis=1) @ g

    weights = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333)
    c1, c2 = 0.01**2, 0.03**2
    per_channel = []
    for ch in range(a.shape[2]):
        x, y, value = a[:, :, ch], b[:, :, ch], 1.0
        for level, weight in enumerate(weights):
            mx, my = blur(x), blur(y)
            vx, vy, cov = blur(x * x) - mx**2, blur(y * y) - my**2, blur(x * y) - mx * my
            cs = ((2 * cov + c2) / (vx + vy + c2)).mean()
            if level < len(weights) - 1:
                value *= max(cs, 0.0) ** weight
                x = x.reshape(x.shape[0] // 2, 2, x.shape[1] // 2, 2).mean((1, 3))
                y = y.reshape(y.shape[0] // 2, 2, y.shape[1] // 2, 2).mean((1, 3))
            else:
                full = ((2 * mx * my + c1) / (mx**2 + my**2 + c1)) * (2 * cov + c2) / (vx + vy + c2)
                value *= max(full.mean(), 0.0) ** weight
        per_channel.append(value)
    return float(np.mean(per_channel))


def test_ms_ssim_matches_its_definition_and_needs_a_large_enough_image():
    rng = np.random.default_rng(1)
    a = rng.random((176, 192, 3)) * np.array([1.0, 0.6, 0.3])  # channels differ, sides differ: a transposed
    b = np.clip(a + rng.normal(0, 0.05, a.shape), 0, 1)       # or channel-mixed layout would not match
    assert metrics.ms_ssim(a, a) == pytest.approx(1.0, abs=1e-6)
    assert metrics.ms_ssim(a, b) == pytest.approx(_direct_ms_ssim(a, b), abs=1e-5)
    assert metrics.ms_ssim(torch.from_numpy(a), torch.from_numpy(b)) == pytest.approx(metrics.ms_ssim(a, b))
    assert metrics.ms_ssim(a[:160], b[:160]) is None  # four halvings leave less than a window


def test_depth_l1_masks_invalid_measurements():
    gt = np.array([[1.0, 0.0], [np.nan, 2.0]])
    pred = np.array([[1.01, 5.0], [5.0, 1.98]])
    assert metrics.depth_l1_cm(pred, gt) == pytest.approx(1.5)
    assert math.isnan(metrics.depth_l1_cm(pred, np.zeros_like(gt)))


def test_lpips_reports_why_it_is_unavailable(monkeypatch, tmp_path):
    monkeypatch.setenv("OGMAP_LPIPS_WEIGHTS", str(tmp_path / "absent.safetensors"))
    ok, reason = metrics.lpips_status()
    assert not ok and reason
    scorer = metrics.Lpips()
    assert scorer.model is None and scorer.reason == reason
    assert scorer(np.zeros((8, 8, 3)), np.zeros((8, 8, 3))) is None


def test_summarise_skips_missing_values():
    frames = [
        {"psnr": 20.0, "ssim": 0.5, "ms_ssim": None, "depth_l1_cm": 2.0, "lpips": None},
        {"psnr": 30.0, "ssim": 0.7, "ms_ssim": 0.9, "depth_l1_cm": math.nan, "lpips": None},
    ]
    summary = metrics.summarise(frames)
    assert summary == {"psnr": 25.0, "psnr_affine": None, "ssim": pytest.approx(0.6), "ms_ssim": 0.9,
                       "depth_l1_cm": 2.0, "lpips": None, "frames": 2,
                       "psnr_spread": {"min": 20.0, "max": 30.0, "std": 5.0}}
    assert metrics.summarise([{"psnr": None}])["psnr_spread"] is None
