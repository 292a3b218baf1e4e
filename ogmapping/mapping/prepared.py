"""A frame made ready to map (``Mapper.prepare``): the per-frame work that needs no map, so any thread may do it
while the mapper maps the frame before.

Two ways, chosen by ``ExecutionProfile.device_frames``:

- on the host (the CPU's): depth registered onto the colour grid and clipped in numpy
  (``ogmapping.frames.preprocess``), then colour, depth and pose as host tensors at the mapper's precision.
- on the device (CUDA's): the raw images and pose copied into pinned memory and uploaded without blocking,
  the depth registered and clipped there (``ogmapping.frames.preprocess_device``), so the host's part is the
  copy into pinned memory. The work runs on a stream of the mapper's for preparing, not on its mapping
  stream: the caller may be another thread while the mapper's stream holds the frame before's steps, and
  neither should queue behind the other. An event recorded after the work is what the mapping stream waits
  for (``wait_on``) before it reads the images; the host never waits for it.
"""

from __future__ import annotations

import dataclasses
import functools
import time
from dataclasses import dataclass

import torch

from ogmapping.frames import preprocess
from ogmapping.frames.frame import Frame
from ogmapping.frames.preprocess_device import prepare_depth
from ogmapping.runtime.profile import ExecutionProfile
from ogmapping.runtime.streams import handed_in


@dataclass(frozen=True)
class PreparedFrame:
    """A frame with its colour, registered and clipped depth, and pose as tensors at the mapper's precision:
    pinned host tensors where the host prepared it on CUDA (they upload without blocking), device tensors
    where the device did."""

    given: Frame  # as it came: its pose, colour intrinsics, index and timestamp are the prepared frame's
    rgb: torch.Tensor
    depth: torch.Tensor
    c2w: torch.Tensor
    seconds: float  # host time spent preparing it
    host: Frame | None = None  # the prepared frame, where the host prepared it
    ready: torch.cuda.Event | None = None  # recorded after the device prepared it, on CUDA

    @functools.cached_property
    def frame(self) -> Frame:
        """The frame as mapped, depth registered onto the colour grid and clipped, on the host. Where the device
        prepared it, its depth is read from there on first use: the host waits for the preparation."""
        if self.host is not None:
            return self.host
        if self.ready is not None:
            self.ready.synchronize()
        depth = self.depth.to("cpu", copy=True).numpy()
        return dataclasses.replace(self.given, depth=depth, depth_intrinsics=self.given.color_intrinsics,
                                   depth_to_color=None)

    def wait_on(self, stream: torch.cuda.Stream | None) -> None:
        """Make ``stream`` (the mapper's) wait for the device's preparation, and mark the images as used there,
        so their memory is not handed out again while it reads them."""
        if self.ready is None or stream is None:
            return
        stream.wait_event(self.ready)
        handed_in(stream, (self.rgb, self.depth, self.c2w))


def prepare_on_host(frame: Frame, depth_min: float, depth_max: float, profile: ExecutionProfile) -> PreparedFrame:
    """``frame`` prepared in numpy, its tensors pinned on CUDA."""
    start = time.perf_counter()
    ready = preprocess.prepare(frame, depth_min, depth_max)
    rgb, depth, c2w = (torch.as_tensor(array, dtype=profile.precision) for array in (ready.rgb, ready.depth, ready.c2w))
    if profile.device.type == "cuda":
        rgb, depth, c2w = rgb.pin_memory(), depth.pin_memory(), c2w.pin_memory()
    return PreparedFrame(frame, rgb, depth, c2w, time.perf_counter() - start, host=ready)


def prepare_on_device(frame: Frame, depth_min: float, depth_max: float, profile: ExecutionProfile,
              stream: torch.cuda.Stream | None) -> PreparedFrame:
    """``frame`` uploaded as it came and prepared on ``profile.device``, on ``stream`` (None on the CPU)."""
    start = time.perf_counter()
    rgb, c2w = (torch.as_tensor(array, dtype=profile.precision) for array in (frame.rgb, frame.c2w))
    depth = torch.as_tensor(frame.depth)  # in its own type, as numpy tests which depth is valid
    if profile.device.type == "cuda":
        rgb, depth, c2w = rgb.pin_memory(), depth.pin_memory(), c2w.pin_memory()
    ready = None
    with torch.cuda.stream(stream):
        rgb, depth, c2w = (tensor.to(profile.device, non_blocking=True) for tensor in (rgb, depth, c2w))
        depth = prepare_depth(depth, frame, depth_min, depth_max).to(profile.precision)
        if stream is not None:
            ready = torch.cuda.Event()
            ready.record(stream)
    return PreparedFrame(frame, rgb, depth, c2w, time.perf_counter() - start, ready=ready)
