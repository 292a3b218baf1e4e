"""The ``ogmap`` command: its subcommands (``commands.py``), the ``run`` loop (``runner.py``) and the
flags it shares with ``ogclient`` (``options.py``).

Kept light: ``ogclient`` imports ``options`` without torch, so ``main`` loads the commands when called.
"""

from __future__ import annotations


def main(argv: list[str] | None = None) -> int:
    """The ``ogmap`` entry point."""
    from ogmapping.cli.commands import main as run_command

    return run_command(argv)
