"""The command line: one entry point, every verb present, fast to start."""

from __future__ import annotations

import subprocess
import sys

from omnigen import __version__
from omnigen.cli import build_parser, main

VERBS = ["render", "convert", "merge", "export", "stats", "show", "validate", "train", "predict", "eval", "bev",
         "eval-kitti", "calib-sensitivity"]


def test_every_verb_is_a_subcommand():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert set(VERBS) <= set(sub.choices)


def test_help_does_not_import_torch():
    """Building the parser imports every command module: they must keep torch inside run()."""
    code = "import sys; from omnigen.cli import build_parser; build_parser(); print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"


def test_version_from_the_installed_entry_point():
    out = subprocess.run([sys.executable, "-m", "omnigen", "--version"], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == f"omnigen {__version__}"


def test_errors_are_one_readable_line(tmp_path, capsys):
    assert main(["export", "coco", str(tmp_path / "missing"), "--out", str(tmp_path / "x.json")]) == 1
    err = capsys.readouterr().err
    assert "not an UrbanOmniView dataset" in err and "Traceback" not in err
