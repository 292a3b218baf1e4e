"""Command-line flags shared by ``ogmap`` and ``ogclient``: dataset, config and camera.

Free of torch, so the client's commands parse them without loading the engine.
"""

from __future__ import annotations

import argparse

from ogmapping.camera import Intrinsics
from ogmapping.config import PRESETS
from ogmapping.datasets import FORMATS


def add_dataset_arguments(parser: argparse.ArgumentParser) -> None:
    """The dataset flags shared by ``ogmap run`` and ``ogclient stream/eval``."""
    parser.add_argument("--data", required=True, help="dataset folder (or 'synthetic')")
    parser.add_argument("--format", default="auto", choices=FORMATS, help="dataset layout (default: detect)")
    parser.add_argument("--frames", default=None, metavar="START:END",
                        help="positions in the sorted frame list to use (default: all)")
    parser.add_argument("--stride", type=int, default=1, help="stream every N-th frame (default 1)")
    parser.add_argument("--scale", type=float, default=1.0, help="image scale, e.g. 0.5 for 320x240 (default 1)")


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    """``--preset``, ``--config FILE`` and ``--set KEY=VALUE``, the inputs of ``config.resolve``."""
    parser.add_argument("--preset", default="sparse", choices=PRESETS, help="method preset (default sparse)")
    parser.add_argument("--config", default=None, help="YAML/JSON file of config overrides")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override one config value, e.g. --set keyframes.iterations=40 (repeatable)")


def parse_intrinsics(text: str, size: str) -> Intrinsics:
    """``--intrinsics fx,fy,cx,cy`` and ``--size WIDTHxHEIGHT`` as checked intrinsics."""
    try:
        fx, fy, cx, cy = (float(v) for v in text.split(","))
        width, height = (int(v) for v in size.lower().split("x"))
    except ValueError as error:
        raise ValueError("--intrinsics must be fx,fy,cx,cy and --size WIDTHxHEIGHT") from error
    intrinsics = Intrinsics(fx, fy, cx, cy, width, height)
    intrinsics.validate()
    return intrinsics
