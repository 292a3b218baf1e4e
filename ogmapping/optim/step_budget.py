"""How many times its configured steps a frame gets, by the image's resolution.

A finer image of the same scene holds more detail for the map to learn; at 1200x680 the steps tuned
at 600x340 leave Replica room0 2.5 dB under its 600x340 score (bench/RESULTS.md "Steps by
resolution"). The multiple grows with the image's linear size, in whole steps, so every image up to
about 1.5 times the reference's width maps exactly as before; ``keyframes.steps_growth`` "area" gives the
step counts its square, a step for each pixel a finer image adds, where quality pays for it.
"""

from __future__ import annotations

import math

from ogmapping.config import KeyframeConfig
from ogmapping.config.by_resolution import grown
from ogmapping.frames.camera import Intrinsics


def step_multiple(settings: KeyframeConfig, intrinsics: Intrinsics) -> int:
    """``sqrt(pixels / steps_reference_pixels)`` rounded half up, at least 1; 1 when the reference is 0."""
    if settings.steps_reference_pixels == 0:
        return 1
    linear = math.sqrt(intrinsics.width * intrinsics.height / settings.steps_reference_pixels)
    return max(1, math.floor(linear + 0.5))


def step_count_multiple(settings: KeyframeConfig, intrinsics: Intrinsics) -> int:
    """What a frame's configured step counts are multiplied by: ``step_multiple`` grown by ``steps_growth``."""
    return grown(step_multiple(settings, intrinsics), settings.steps_growth)
