"""Which frames of a source are streamed and which are held out as novel views.

Positions count the reader's sorted frame list, never numbers in file names.
"""

from __future__ import annotations

from dataclasses import dataclass

HELDOUT_MODULUS = 10
HELDOUT_REMAINDER = 5


def parse_frame_range(text: str | None, length: int) -> range:
    """``"START:END"`` (either side may be empty) -> a clamped range of positions."""
    if not text:
        return range(length)
    start_text, sep, end_text = text.partition(":")
    if not sep:
        raise ValueError(f"--frames must look like START:END, got {text!r}")
    try:
        start = int(start_text) if start_text else 0
        end = int(end_text) if end_text else length
    except ValueError as error:
        raise ValueError(f"--frames must hold integers, got {text!r}") from error
    if start < 0 or end < start:
        raise ValueError(f"--frames {text!r} is empty or negative")
    if start >= length:
        raise ValueError(f"--frames {text!r} starts past the last frame (the source has {length})")
    return range(start, min(end, length))


def is_heldout(position: int) -> bool:
    return position % HELDOUT_MODULUS == HELDOUT_REMAINDER


@dataclass(frozen=True)
class Selection:
    streamed: list[int]
    heldout: list[int]


def select(length: int, frames: str | None = None, stride: int = 1) -> Selection:
    """Positions to stream (every ``stride``-th non-held-out one) and the held-out positions."""
    if stride < 1:
        raise ValueError(f"--stride must be >= 1, got {stride}")
    positions = parse_frame_range(frames, length)
    heldout = [p for p in positions if is_heldout(p)]
    streamed = [p for p in positions if not is_heldout(p)][::stride]
    return Selection(streamed=streamed, heldout=heldout)
