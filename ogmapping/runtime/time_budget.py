"""How long one frame's optimisation may run, and a flag that stops it sooner.

The mapper checks the budget between optimisation iterations, so stopping costs at most one
iteration's time; what the frame learnt until then stays in the map. A server gives each frame a
wall-clock budget and cancels the one being mapped when its session closes or the server stops.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass, field
from enum import StrEnum


class Stop(StrEnum):
    DEADLINE = "deadline"  # the frame used up its time
    CANCELLED = "cancelled"  # its owner asked it to stop (a session closing, a server shutting down)


@dataclass(frozen=True)
class Budget:
    seconds: float = math.inf  # from the start of the frame's processing
    cancelled: threading.Event = field(default_factory=threading.Event)

    def stop(self, started: float) -> Stop | None:
        """Why a frame whose processing began at ``started`` (``time.perf_counter()``) must stop now, if it must."""
        if self.cancelled.is_set():
            return Stop.CANCELLED
        if time.perf_counter() - started >= self.seconds:
            return Stop.DEADLINE
        return None
