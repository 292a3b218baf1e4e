"""One CUDA stream per mapper, so that mappers driven from separate threads overlap on the device.

On the default stream every session's kernels would queue behind every other's. A mapper makes
its own stream (torch's pool streams do not wait on the default one) and runs all its device work
on it; the tensors it creates and keeps are only ever used there. What crosses the boundary:

- in: tensors the caller made on its own stream (a map state on the device). ``on_stream`` makes
  the mapper's stream wait for the caller's work queued so far, and ``handed_in`` marks such
  tensors as used on the mapper's stream, so their memory is not reused under it.
- out: host copies (``.cpu()`` inside the block waits for the copy) need nothing; device tensors
  returned go through ``handed_out``: the caller's stream waits for the mapper's, and the tensors
  are marked as used on the caller's stream.

Neither side makes the host wait for the device. On the CPU every helper does nothing.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from contextlib import contextmanager

import torch


def session_stream(device: torch.device) -> torch.cuda.Stream | None:
    """A stream of its own for a mapper on ``device``; None on the CPU."""
    return torch.cuda.Stream(device) if device.type == "cuda" else None


@contextmanager
def on_stream(stream: torch.cuda.Stream | None) -> Iterator[None]:
    """Run the block's device work on ``stream``, after the work the caller queued on its own."""
    if stream is None:
        yield
        return
    caller = torch.cuda.current_stream(stream.device)
    if caller != stream:
        stream.wait_stream(caller)
    with torch.cuda.stream(stream):
        yield


def handed_in(stream: torch.cuda.Stream | None, tensors: Iterable[torch.Tensor]) -> None:
    """Mark the caller's device ``tensors`` as used on ``stream`` (the mapper may keep them)."""
    if stream is None:
        return
    for tensor in tensors:
        if tensor.is_cuda:
            tensor.record_stream(stream)


def handed_out(stream: torch.cuda.Stream | None, tensors: Iterable[torch.Tensor]) -> None:
    """Make the caller's current stream wait for ``stream`` before it reads ``tensors``, which were
    made on ``stream``, and mark them as used on the caller's stream. Call outside ``on_stream``."""
    if stream is None:
        return
    caller = torch.cuda.current_stream(stream.device)
    if caller == stream:
        return
    caller.wait_stream(stream)
    for tensor in tensors:
        if tensor.is_cuda:
            tensor.record_stream(caller)
