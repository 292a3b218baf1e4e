"""Which dataset frames a command streams or scores, chosen exactly as ``ogmap run`` chooses them."""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import Any

from ogmapping.datasets import FrameSource, open_dataset
from ogmapping.frame import Frame
from ogmapping.preprocess import resize_frame
from ogmapping.selection import Selection, select


@dataclass
class FrameSet:
    source: FrameSource
    selection: Selection
    scale: float = 1.0

    def load(self, position: int) -> Frame:
        frame = self.source[position]
        return resize_frame(frame, self.scale) if self.scale != 1.0 else frame


def open_frames(
    data: str, format: str = "auto", frames: str | None = None, stride: int = 1, scale: float = 1.0,
    **options: Any,
) -> FrameSet:
    source = open_dataset(data, format, **options)
    selection = select(len(source), frames, stride)
    if not selection.streamed:
        raise ValueError("the frame selection leaves no frame to stream")
    return FrameSet(source, selection, scale)


def from_args(args: argparse.Namespace) -> FrameSet:
    """From the flags of ``ogmapping.cli.add_dataset_arguments``."""
    return open_frames(args.data, args.format, args.frames, args.stride, args.scale)
