"""Frames prepared on CUDA (``ExecutionProfile.device_frames``): equal to numpy's preparation, with no host wait.

A real 7-Scenes frame at 640x480 (``$OGMAP_GPU_DATA`` or ../shared/data) is uploaded from pinned memory and
registered and clipped on its own stream under ``torch.cuda.set_sync_debug_mode("error")`` (any operator or
copy that makes the host wait raises), and must equal numpy's depth bit for bit. The registration's time per
frame on the device (CUDA events, median of 20) and numpy's on the host go to the terminal and to
``$OGMAP_GPU_REPORT/preprocess-device.json`` (``bench/gpu/check.sh`` sets it): reported, not asserted.
"""

from __future__ import annotations

import json
import os
import statistics
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from triton_kernels import median_ms

from ogmapping.config import resolve
from ogmapping.datasets.sevenscenes import SevenScenes
from ogmapping.frames import preprocess
from ogmapping.frames.preprocess_device import prepare_depth
from ogmapping.mapper import Mapper

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")]


def test_a_real_frame_prepared_on_cuda_equals_numpy_s_without_a_host_wait(
        seven_scenes_if_present: Path | None) -> None:
    data = os.environ.get("OGMAP_GPU_DATA") or seven_scenes_if_present
    if data is None:
        pytest.skip("needs 7-Scenes RedKitchen ($OGMAP_GPU_DATA or ../shared/data): a real depth camera beside "
                    "the colour camera")
    frame = SevenScenes(Path(data))[0]
    assert frame.depth.shape == (480, 640) and frame.depth_to_color is not None
    mapper = Mapper(resolve("sparse"), "cuda")
    assert mapper.profile.device_frames
    settings = mapper.config.octree
    expected = preprocess.prepare(frame, settings.depth_min, settings.depth_max).depth
    mapper.prepare(frame)  # the allocators' caches settle
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")
    try:
        prepared = mapper.prepare(frame)
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert prepared.depth.is_cuda and prepared.ready is not None
    np.testing.assert_array_equal(prepared.frame.depth, expected)  # read back once the preparation is done

    depth = torch.as_tensor(frame.depth, device="cuda")
    device_ms = median_ms(lambda: prepare_depth(depth, frame, settings.depth_min, settings.depth_max))
    host_ms = []
    for _ in range(5):
        start = time.perf_counter()
        preprocess.prepare(frame, settings.depth_min, settings.depth_max)
        host_ms.append(1e3 * (time.perf_counter() - start))
    figures = {"gpu": torch.cuda.get_device_name(), "torch": torch.__version__,
               "frame": "7-Scenes RedKitchen 0, 640x480", "device_ms": device_ms,
               "numpy_host_ms": statistics.median(host_ms), "prepare_host_ms": 1e3 * prepared.seconds}
    print(f"\nframe preparation at 640x480 on {figures['gpu']}: registration and clipping {device_ms:.3f} ms on the "
          f"device, numpy {figures['numpy_host_ms']:.1f} ms on the host; the device path's host time "
          f"{figures['prepare_host_ms']:.2f} ms")
    folder = os.environ.get("OGMAP_GPU_REPORT")
    if folder:
        Path(folder).mkdir(parents=True, exist_ok=True)
        (Path(folder) / "preprocess-device.json").write_text(json.dumps(figures, indent=2) + "\n")
