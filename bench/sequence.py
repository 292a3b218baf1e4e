"""The frames the tuning scripts map and score: one set of flags, decoded once before any clock starts."""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from dataclasses import dataclass

from ogmapping.config import MapperConfig, parse_override_args, resolve
from ogmapping.datasets import open_dataset
from ogmapping.frames.frame import Frame
from ogmapping.frames.preprocess import resize_frame
from ogmapping.frames.selection import Selection, select
from ogmapping.mapper import Mapper


@dataclass
class Sequence:
    selection: Selection
    streamed: list[Frame]
    heldout: list[Frame]  # positions with index % 10 == 5, never streamed


def add_sequence_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", default="../shared/data/7scenes-redkitchen")
    parser.add_argument("--frames", default="0:300", help="START:END (default 0:300)")
    parser.add_argument("--scale", type=float, default=0.5, help="image scale (default 0.5: 320x240)")
    parser.add_argument("--preset", default="sparse")


def load_sequence(args: argparse.Namespace) -> Sequence:
    source = open_dataset(args.data)
    selection = select(len(source), args.frames, 1)
    return Sequence(
        selection,
        [resize_frame(source[i], args.scale) for i in selection.streamed],
        [resize_frame(source[i], args.scale) for i in selection.heldout],
    )


@dataclass
class MappedRun:
    config: MapperConfig
    mapper: Mapper
    keyframes: int
    seconds: float  # the mapping loop alone

    def fps(self, frames: int) -> float:
        return frames / self.seconds


def map_setting(preset: str, setting: str, frames: list[Frame],
                after: Callable[[Frame, Mapper], None] | None = None) -> MappedRun:
    """Map ``frames`` under ``preset`` plus the overrides in ``setting`` ("KEY=VALUE KEY=VALUE"); ``after`` is
    called with each frame once it is mapped, off the clock."""
    config = resolve(preset, overrides=parse_override_args(setting.split()))
    mapper = Mapper(config)
    keyframes, seconds = 0, 0.0
    for frame in frames:
        start = time.perf_counter()
        keyframes += mapper.process(frame).keyframe
        seconds += time.perf_counter() - start
        if after is not None:
            after(frame, mapper)
    return MappedRun(config, mapper, keyframes, seconds)
