"""The command line: one entry point, every verb present, honest about what is not built."""

from __future__ import annotations

import subprocess
import sys

import pytest

from omnigen import __version__
from omnigen.cli import NOT_BUILT, build_parser, main

VERBS = ["render", "convert", "merge", "export", "stats", "show", "validate", "train", "predict", "eval", "bev"]


def test_every_verb_is_a_subcommand():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert set(VERBS) <= set(sub.choices)


@pytest.mark.parametrize("verb", sorted(NOT_BUILT))
def test_unbuilt_verbs_say_so_and_fail(verb, capsys):
    assert main([verb, "anything"]) == 2
    assert "not built yet" in capsys.readouterr().err


def test_version_from_the_installed_entry_point():
    out = subprocess.run([sys.executable, "-m", "omnigen", "--version"], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == f"omnigen {__version__}"


def test_errors_are_one_readable_line(tmp_path, capsys):
    assert main(["export", "coco", str(tmp_path / "missing"), "--out", str(tmp_path / "x.json")]) == 1
    err = capsys.readouterr().err
    assert "not an UrbanOmniView dataset" in err and "Traceback" not in err
