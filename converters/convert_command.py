"""Convert a public dataset (kitti, dair) into UrbanOmniView.

One subcommand per entry of CONVERTERS (converters/__init__.py), each a converter module with its
own add_arguments(parser) and run(args): adding a dataset touches no CLI code.
"""

from __future__ import annotations

import argparse
import importlib

from omnigen.converters import CONVERTERS


def add_arguments(p: argparse.ArgumentParser) -> None:
    from omnigen import cli

    cli.add_commands(p.add_subparsers(dest="converter", required=True, metavar="DATASET"), CONVERTERS)


def run(args: argparse.Namespace) -> int:
    """Never called: argparse dispatches to each converter's own run, which that converter's
    subparser sets as its default `func`, overriding the one cli.add_commands sets here. It exists
    because every command module the registry names gives run(args)."""
    return importlib.import_module(CONVERTERS[args.converter]).run(args)
