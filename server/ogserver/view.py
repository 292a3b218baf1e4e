"""``ogserver view MAP``: one snapshot's (.safetensors) or recording's (.mcap) map in the web view on
127.0.0.1, behind a random token, until SIGTERM or SIGINT; no gRPC port, no sessions.

It prints its progress, then ``ogserver map view on URL`` once the page is served (the token in the
URL's query). A map it cannot read is one line on stderr, ``ogserver view: ...``, and exit status 2.
``ogclient view`` runs it as a child process, as ``make demo`` runs the gRPC server.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
from pathlib import Path
from typing import NoReturn

from ogserver.web import assets

READY_PREFIX = "ogserver map view on"
ERROR_PREFIX = "ogserver view:"


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="ogserver view", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("map", help="a snapshot (.safetensors) or a recording (.mcap: its final snapshot beside it, "
                               "else its frames mapped here as a replay would)")
    p.add_argument("--port", type=int, default=0, help="port on 127.0.0.1 (default: any free one)")
    p.add_argument("--device", default="auto", help="where to load and decode the map: auto, cpu, cuda")
    p.add_argument("--quiet", action="store_true", help="no progress bar while a recording's frames are mapped")
    return p


def progress(line: str) -> None:
    print(line, flush=True)


def serve(path: Path, port: int, device: str, bar: bool = True) -> NoReturn:
    """Load the map and serve it until a signal ends the process."""
    if not path.is_file():
        raise ValueError(f"{path}: no such file")
    if assets.missing():
        raise ValueError("the web view's browser libraries are not installed: run python -m ogserver.web.assets "
                         "(make venv does)")
    from ogserver.web import still  # torch and the engine load only once the arguments are sound

    _, url = still.serve(still.open_map(path, device, progress, bar), port)  # on a thread of its own
    print(f"{READY_PREFIX} {url}", flush=True)
    while True:
        signal.pause()


def stop_at_once(*_: object) -> None:
    """SIGTERM or SIGINT: a map that no longer changes has nothing to save, so the process ends at once, a
    replay under way too (a KeyboardInterrupt raised into the engine's compiled kernels ends it untidily)."""
    os._exit(0)


def main(argv: list[str]) -> int:
    """Serves until SIGTERM or SIGINT ends the process (status 0); 2 for a map it cannot read."""
    args = parser().parse_args(argv)
    for number in (signal.SIGINT, signal.SIGTERM):
        signal.signal(number, stop_at_once)
    try:
        serve(Path(args.map), args.port, args.device, not args.quiet)
    except (ValueError, OSError) as error:
        print(f"{ERROR_PREFIX} {error}", file=sys.stderr)
    return 2
