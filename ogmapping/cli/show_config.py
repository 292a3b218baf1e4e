"""``ogmap config``: what a preset (and any overrides) resolves to for a first frame of a given size."""

from __future__ import annotations

import argparse
import json

from ogmapping.cli.options import add_config_arguments
from ogmapping.config import parse_override_args, resolution, resolve


def parse_size(text: str) -> tuple[int, int]:
    """``WIDTHxHEIGHT`` as two positive ints."""
    try:
        width, height = (int(part) for part in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"--resolution must be WIDTHxHEIGHT, e.g. 1200x680, got {text!r}") from None
    if width < 1 or height < 1:
        raise ValueError(f"--resolution must be positive, got {text!r}")
    return width, height


def command_config(args: argparse.Namespace) -> int:
    config = resolve(args.preset, args.config, parse_override_args(args.overrides))
    width, height = parse_size(args.resolution)
    reference = config.resolution.reference_pixels
    multiple = resolution.step_multiple(reference, width, height)
    resolved = resolution.resolve(config, multiple)
    if args.json:
        print(json.dumps(resolved.config.to_dict(), indent=2, sort_keys=True))
        return 0
    basis = (f"sqrt({width * height} / {reference} reference pixels), rounded" if reference
             else "resolution.reference_pixels is 0")
    print(f"{args.preset} at {width}x{height}: step multiple {multiple} ({basis})")
    rows = [("setting", "rule", "value")]
    for name, follower in resolution.FOLLOWERS.items():
        section, field = follower.key.split(".")
        before = getattr(getattr(config, section), field)
        after = getattr(getattr(resolved.config, section), field)
        value = f"{before!r} -> {after!r}" if name in resolved.changed else repr(before)
        rows.append((follower.key, getattr(config.resolution, name), value))
    widths = [max(len(row[column]) for row in rows) for column in range(2)]
    for key, rule, value in rows:
        print(f"  {key:<{widths[0]}}  {rule:<{widths[1]}}  {value}")
    what = "rebuilt" if resolved.reshaped else "kept"
    print(f"the model's shape is {what} on the first frame; --json prints the whole resolved config")
    return 0


def add_config_command(commands: argparse._SubParsersAction) -> None:
    """``ogmap config``'s parser, handled by ``command_config``."""
    show = commands.add_parser(
        "config", help="print what a preset resolves to for a first frame of a given size",
        description="Resolves the preset, --config file and --set overrides as `ogmap run` does, then applies "
        "the resolution rules (resolution.*: how settings follow the image's step multiple, 1 up to about "
        "900x510, 2 at 1200x680) for a first frame of --resolution, and prints each rule and the value it gives.")
    add_config_arguments(show)
    show.add_argument("--resolution", required=True, metavar="WIDTHxHEIGHT", help="the first frame's size")
    show.add_argument("--json", action="store_true", help="print the whole resolved config as JSON")
    show.set_defaults(handler=command_config)
