"""Frames prepared ahead (``Mapper.prepare``, on another thread) map exactly as plain frames do.

The per-frame work that needs no map (depth registration onto the colour grid, clipping, the host
tensors) runs off the mapping thread in the CLI and the server; the map must not notice, and the
stage timers must say where that work ran.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import torch
from safetensors.torch import load

from ogmapping.config import resolve
from ogmapping.mapper import Mapper, PreparedFrame
from ogmapping.quality.evaluation import open_frames

OVERRIDES = {"keyframes.first_iterations": "2", "keyframes.iterations": "1"}


def mapped(ahead: bool) -> Mapper:
    frames = open_frames("synthetic", "synthetic", "0:4", scale=0.25)
    mapper = Mapper(resolve("sparse", overrides=OVERRIDES), "cpu")
    with ThreadPoolExecutor(max_workers=1) as pool:
        for position in frames.selection.streamed:
            frame = frames.load(position)
            mapper.process(pool.submit(mapper.prepare, frame).result() if ahead else frame)
    return mapper


def test_a_frame_prepared_on_another_thread_maps_as_the_plain_frame_does() -> None:
    plain, ahead = mapped(False), mapped(True)
    left, right = load(plain.snapshot()), load(ahead.snapshot())
    assert left.keys() == right.keys()
    for name, tensor in left.items():
        assert torch.equal(tensor, right[name]), name
    assert "preprocess" in plain.timings and "preprocess_ahead" not in plain.timings
    assert "preprocess_ahead" in ahead.timings and "preprocess" not in ahead.timings
    assert ahead.timings["preprocess_ahead"] > 0 and ahead.timings["upload"] > 0


def test_a_prepared_frame_holds_its_registered_images_as_host_tensors() -> None:
    frames = open_frames("synthetic", "synthetic", "0:1", scale=0.25)
    mapper = Mapper(resolve("sparse", overrides=OVERRIDES), "cpu")
    prepared = mapper.prepare(frames.load(frames.selection.streamed[0]))
    assert isinstance(prepared, PreparedFrame) and prepared.seconds > 0
    frame = prepared.frame
    assert prepared.rgb.shape == (frame.color_intrinsics.height, frame.color_intrinsics.width, 3)
    assert prepared.depth.shape == frame.depth.shape and prepared.depth.dtype == mapper.profile.precision
    assert torch.equal(prepared.depth, torch.as_tensor(frame.depth, dtype=mapper.profile.precision))
