"""Commands printed for the user to paste: the venv's entry points by path, session files under out/."""

from __future__ import annotations

import sys

import pytest
from ogclient import shell
from ogclient.__main__ import parser


def test_commands_name_the_venvs_entry_point_relative_to_here(tmp_path, monkeypatch) -> None:
    bin_dir = tmp_path / ".venv" / "bin"
    bin_dir.mkdir(parents=True)
    (bin_dir / "ogclient").write_text("#!/bin/sh\n")
    monkeypatch.setattr(sys, "executable", str(bin_dir / "python"))
    monkeypatch.chdir(tmp_path)
    assert shell.command("ogclient") == ".venv/bin/ogclient"
    monkeypatch.chdir(tmp_path / ".venv")
    assert shell.command("ogclient") == "bin/ogclient"
    assert shell.command("ogmap") == "ogmap"  # not installed there: the bare name


@pytest.mark.parametrize("command", [["create"], ["stream", "--data", "x"], ["replay", "x.mcap"],
                                     ["restore", "x.safetensors"]])
def test_session_files_go_under_out_by_default(command: list[str]) -> None:
    assert parser().parse_args(command).session_out == "out/session.json"
