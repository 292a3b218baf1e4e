"""A headless browser for the web view's tests: Debian's chromium, driven by Playwright, WebGL through
SwiftShader. Tests that need it skip, saying why, where playwright or chromium is missing."""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from contextlib import contextmanager
from urllib.parse import urlencode

import numpy as np
import pytest

from ogmapping.frames.camera import Intrinsics

CHROMIUM = os.environ.get("OGMAP_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
FLAGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist"]
PAGE_SECONDS = 60.0


def requirement() -> str | None:
    """Why the browser tests cannot run here, or None."""
    try:
        import playwright.sync_api  # noqa: F401
    except ImportError:
        return "playwright is not installed (the dev extra: pip install -e '.[dev]')"
    if CHROMIUM is None:
        return "chromium is not installed (Debian: apt-get install chromium; .ci/run installs it)"
    return None


needs_browser = pytest.mark.skipif(requirement() is not None, reason=str(requirement()))


@contextmanager
def browser() -> Iterator:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as playwright:
        launched = playwright.chromium.launch(executable_path=CHROMIUM, args=FLAGS, headless=True)
        try:
            yield launched
        finally:
            launched.close()


def fragment(c2w: np.ndarray, camera: Intrinsics) -> str:
    """The page's camera: ``#pose=...&fx=..&fy=..&cx=..&cy=..&size=WxH``."""
    pose = ",".join(repr(float(value)) for value in np.asarray(c2w).ravel())
    return "#" + urlencode({"pose": pose, "fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy,
                            "size": f"{camera.width}x{camera.height}"}, safe=",")


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """Of two images in [0, 1]."""
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return float("inf") if mse == 0 else 10 * np.log10(1.0 / mse)
