"""Keyframes captured from CUDA: copied to pinned host memory without the host waiting, read once there."""

from __future__ import annotations

import pytest
import torch

from ogmapping.frames.camera import Intrinsics
from ogmapping.optim.keyframes import Keyframe
from ogmapping.structure.footprint import Footprint

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")]


def test_a_keyframe_leaves_the_device_without_a_wait_and_arrives_whole():
    generator = torch.Generator().manual_seed(0)
    rgb, depth = torch.rand(480, 640, 3, generator=generator), torch.rand(480, 640, generator=generator) * 4
    codes = Footprint.of_codes(torch.arange(3))
    camera = Intrinsics(500.0, 500.0, 320.0, 240.0, 640, 480)
    expected = Keyframe.capture(0, rgb, depth, camera, torch.eye(4), codes)
    rgb_cuda, depth_cuda, pose = rgb.cuda(), depth.cuda(), torch.eye(4, device="cuda")
    torch.cuda.synchronize()
    torch.cuda.set_sync_debug_mode("error")  # any copy that makes the host wait raises
    try:
        stored = Keyframe.capture(0, rgb_cuda, depth_cuda, camera, pose, codes, pinned=True)
        again = stored.view(torch.device("cuda"), compiled=False)  # copied back in stream order
        on_device = stored.device_depth(torch.device("cuda"))
    finally:
        torch.cuda.set_sync_debug_mode("default")
    assert stored.ready is not None and stored.host_rgb.is_pinned() and stored.host_depth.is_pinned()
    assert torch.equal(stored.rgb, expected.rgb) and torch.equal(stored.depth, expected.depth)
    assert stored.ready is None, "read once on the host, the copy is waited for once"
    assert torch.equal(again.rgb.cpu(), expected.rgb.float() / 255.0)
    assert torch.equal(on_device.cpu(), expected.depth.float())
