"""Server settings: defaults, overridden by a YAML/JSON file, overridden by command-line flags."""

from __future__ import annotations

import dataclasses
import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from ogmapping.config import ConfigBounds

MIB = 1 << 20


@dataclass
class Limits:
    """What one client may ask of the server; exceeding any gives RESOURCE_EXHAUSTED."""

    max_sessions: int = 4
    queue_depth: int = 8  # frames read ahead per session before backpressure
    max_image_pixels: int = 4096 * 3072  # per colour/depth image and per render
    max_message_bytes: int = 64 * MIB  # gRPC send/receive limit
    max_anchors: int = 0  # frames are refused once a map holds this many anchors; 0 = no limit
    max_snapshot_bytes: int = 2048 * MIB  # largest snapshot RestoreSession accepts

    def validate(self) -> None:
        for item in dataclasses.fields(self):
            value = getattr(self, item.name)
            minimum = 0 if item.name == "max_anchors" else 1
            if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
                raise ValueError(f"limits.{item.name} must be an integer >= {minimum} (got {value!r})")


@dataclass
class Settings:
    address: str = "127.0.0.1:50051"
    record_dir: str = "recordings"
    device: str = "auto"  # auto, cpu, cuda, cuda:N
    final_snapshots: bool = False  # write <session>.safetensors next to the recording on close
    torch_threads: int = 0  # 0: min(cpu count, 8)
    grace_seconds: float = 5.0  # how long shutdown waits for calls in flight
    warm_up: bool = True  # map a tiny synthetic scene before serving, so the first session pays no load costs
    limits: Limits = field(default_factory=Limits)
    # --- input: what one session's config and one frame may cost
    config_bounds: ConfigBounds = field(default_factory=ConfigBounds)  # on CreateSession's and snapshots' configs
    frame_seconds: float = 60.0  # a frame's optimisation stops after this long, or at once on close; 0 = no limit

    def validate(self) -> None:
        if not self.address or ":" not in self.address:
            raise ValueError(f"address must be HOST:PORT (got {self.address!r})")
        if self.torch_threads < 0 or self.grace_seconds < 0:
            raise ValueError("torch_threads and grace_seconds must not be negative")
        self.limits.validate()
        self.config_bounds.validate()
        if not (math.isfinite(self.frame_seconds) and self.frame_seconds >= 0):
            raise ValueError(f"frame_seconds must be >= 0 and finite (got {self.frame_seconds})")

    def threads(self) -> int:
        return self.torch_threads or max(1, min(os.cpu_count() or 1, 8))


def _assign(target: Any, data: dict[str, Any], prefix: str = "") -> None:
    names = {item.name: item for item in dataclasses.fields(target)}
    for key, value in data.items():
        if key not in names:
            raise ValueError(f"unknown server setting '{prefix}{key}'")
        current = getattr(target, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                raise ValueError(f"server setting {prefix}{key} must be a mapping")
            _assign(current, value, f"{prefix}{key}.")
        else:
            expected = type(current)
            if expected is float and isinstance(value, int) and not isinstance(value, bool):
                value = float(value)
            if type(value) is not expected:
                raise ValueError(f"server setting {prefix}{key} must be {expected.__name__} (got {value!r})")
            setattr(target, key, value)


def load(path: str | Path | None = None, flags: dict[str, Any] | None = None) -> Settings:
    """Defaults, then the file (YAML or JSON, same names, limits nested), then flags not None."""
    settings = Settings()
    if path is not None:
        text = Path(path).read_text()
        data = json.loads(text) if str(path).endswith(".json") else yaml.safe_load(text)
        if not isinstance(data, dict):
            raise ValueError(f"server config {path} must hold a mapping")
        _assign(settings, data)
    for key, value in (flags or {}).items():
        if value is None:
            continue
        target = settings.limits if hasattr(settings.limits, key) else settings
        _assign(target, {key: value})
    settings.validate()
    return settings
