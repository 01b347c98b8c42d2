"""The command line: one entry point, every verb present, fast to start."""

from __future__ import annotations

import argparse
import importlib
import subprocess
import sys

import pytest

from omnigen.converters import CONVERTERS
from omnigen import __version__
from omnigen import cli
from omnigen.cli import COMMANDS, EXPORTERS, build_parser, main

VERBS = ["render", "convert", "merge", "export", "stats", "show", "validate", "train", "train-crop", "predict", "eval", "bev",
         "eval-kitti", "calib-sensitivity"]


def _subcommands(parser: argparse.ArgumentParser, dest: str) -> dict[str, argparse.ArgumentParser]:
    return next(a for a in parser._actions if a.dest == dest).choices


def test_every_verb_is_a_subcommand():
    parser = build_parser()
    sub = _subcommands(parser, "command")
    assert set(VERBS) <= set(sub)
    # each plugged-in verb runs its own module's run(), not a stand-in
    plugged = {**COMMANDS, **{f"export {k}": v for k, v in EXPORTERS.items()},
               **{f"convert {k}": v for k, v in CONVERTERS.items()}}
    for verb, module_name in plugged.items():
        words = verb.split()
        p = sub[words[0]]
        if len(words) == 2:
            p = _subcommands(p, "format" if words[0] == "export" else "converter")[words[1]]
        assert p.get_default("func") is importlib.import_module(module_name).run, verb


def test_every_verb_is_a_command_module():
    """The registry is the one list: every verb, built in or not, is a module with add_arguments and run."""
    assert list(COMMANDS) == VERBS
    for module_name in COMMANDS.values():
        assert module_name.endswith("_command"), module_name


def test_a_missing_command_module_is_an_error(monkeypatch):
    """No "not built yet" stub: a registry entry whose module does not import breaks the parser."""
    monkeypatch.setitem(cli.COMMANDS, "ghost", "omnigen.detector.no_such_command")
    with pytest.raises(ImportError, match="omnigen ghost: command module omnigen.detector.no_such_command"):
        build_parser()


def test_a_command_module_that_fails_inside_is_named(monkeypatch, tmp_path):
    """A module that exists but whose own import fails is reported by its name, not only the inner one's."""
    (tmp_path / "broken_command.py").write_text('"""Broken."""\nimport no_such_dependency_of_omnigen\n')
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setitem(cli.EXPORTERS, "broken", "broken_command")
    with pytest.raises(ImportError, match="command module broken_command does not import: .*no_such_dependency"):
        build_parser()


def test_help_imports_no_heavy_dependency():
    """Building the parser imports every command module: they must keep torch, scipy (0.3 s of a
    0.7 s `omnigen --help` when bev_command loaded it), cv2 and the renderers where they are used."""
    heavy = ("torch", "scipy", "cv2", "pyrender", "OpenGL", "bpy")
    code = (f"import sys; from omnigen.cli import build_parser; build_parser(); "
            f"print([m for m in {heavy!r} if m in sys.modules])")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_version_from_the_installed_entry_point():
    out = subprocess.run([sys.executable, "-m", "omnigen", "--version"], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == f"omnigen {__version__}"


def test_errors_are_one_readable_line(tmp_path, capsys):
    assert main(["export", "coco", str(tmp_path / "missing"), "--out", str(tmp_path / "x.json")]) == 1
    err = capsys.readouterr().err
    assert "not an UrbanOmniView dataset" in err and "Traceback" not in err


def _options(parser, prefix=()):
    """(command words, action) for every option of every command and subcommand."""
    import argparse

    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                yield from _options(sub, (*prefix, name))
        elif action.option_strings and action.dest not in ("help", "version"):
            yield prefix, action, parser


def test_every_numeric_option_is_checked_when_parsed_and_every_default_is_shown():
    """Issue 44: a number that parses is not one a command can use (`--batch -1` processed no
    image), so every numeric option has a type of omnigen.options, which names its range; issue
    45: `render --help` did not say the default quality. Every option's help shows its default."""
    from omnigen.cli import build_parser

    bare, unshown = [], []
    for words, action, parser in _options(build_parser()):
        name = f"omnigen {' '.join(words)} {action.option_strings[-1]}"
        if action.type in (int, float):
            bare.append(name)
        if action.default not in (None, False, [], "") and action.help is not None:
            text = parser.formatter_class(prog="x")._get_help_string(action) or ""
            if "default" not in text:
                unshown.append(name)
    assert not bare, f"numeric options without a checked type: {bare}"
    assert not unshown, f"options whose help does not show the default: {unshown}"
