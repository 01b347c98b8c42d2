"""The `omnigen` command: one entry point, short verbs, a summary table at the end.

Exit codes: 0 success; 1 the command ran and found problems (bad frames skipped, invalid dataset);
2 usage errors.

This file is the command registry and nothing more. Every verb is a `*_command.py` module beside
the part it drives (render in rigs, convert in converters, merge, validate, export, stats and show
in the core, train, predict, eval and bev in the detector), exposing add_arguments(parser) and
run(args) -> int; its help line is its docstring's first line. The registry names the modules as
strings and imports each one when the parser is built: the core (omnigen/*.py) imports no part,
and this is the one place that names them (tests/core/test_layers.py checks both). Building the
parser imports every command module, so they import their heavy dependencies (torch, scipy, cv2, the
renderers) only in run() or the function that uses them, and `omnigen --help` stays fast.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from omnigen import __version__

COMMANDS: dict[str, str] = {
    # verb: module exposing add_arguments(parser) and run(args) -> int, in the order --help lists them
    "render": "omnigen.rigs.render_command",
    "convert": "omnigen.converters.convert_command",  # one subcommand per omnigen.converters.CONVERTERS
    "merge": "omnigen.merge_command",
    "export": "omnigen.export_command",  # coco and yolo, then one subcommand per EXPORTERS entry
    "stats": "omnigen.stats_command",
    "show": "omnigen.show_command",
    "validate": "omnigen.validate_command",
    "train": "omnigen.detector.train_command",
    "train-crop": "omnigen.detector.crop_train_command",
    "predict": "omnigen.detector.predict_command",
    "eval": "omnigen.detector.eval_command",
    "bev": "omnigen.detector.bev_command",
    "eval-kitti": "omnigen.detector.kitti_eval_command",
    "calib-sensitivity": "omnigen.detector.calib_command",
}


EXPORTERS: dict[str, str] = {
    # `omnigen export FORMAT` for the formats a part writes: module exposing add_arguments and run
    "kitti": "omnigen.converters.kitti_export",
    "kitti-tracking": "omnigen.converters.kitti_tracking_export",
    "onnx": "omnigen.detector.prediction.export_onnx",
}


class HelpFormatter(argparse.HelpFormatter):
    """argparse's help with every option's default shown, as Ultralytics' CLI shows its
    defaults: "(default: X)" is added to each help line that does not already say its default."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        shown = action.default not in (None, False, argparse.SUPPRESS, [], "")
        if action.option_strings and shown and "default" not in text:
            text = f"{text} (default: %(default)s)".lstrip()
        return text


def add_commands(subparsers: argparse._SubParsersAction, registry: dict[str, str]) -> None:
    """One subcommand per registry entry; the module gives add_arguments(parser) and run(args).

    There is no fallback for a module that does not import: a missing or broken command module is
    an error naming it, here, not a stub that says "not built yet" (which let a deleted module pass
    every test). Verbs with subcommands of their own (export, convert) call this too.
    """
    for name, module_name in registry.items():
        try:
            module = importlib.import_module(module_name)
        except ImportError as exc:
            raise ImportError(f"omnigen {name}: command module {module_name} does not import: {exc}",
                              name=module_name) from exc
        first = (module.__doc__ or module_name).strip().splitlines()[0]
        if first[1:2].islower():  # "Train the ..." -> "train the ...", as argparse's help reads; not "KITTI"
            first = first[:1].lower() + first[1:]
        q = subparsers.add_parser(name, help=first.rstrip("."), formatter_class=HelpFormatter)
        module.add_arguments(q)
        q.set_defaults(func=module.run)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="omnigen",
        description="Training data for calibration-free monocular 3D object detection in cities.",
    )
    parser.add_argument("--version", action="version", version=f"omnigen {__version__}")
    add_commands(parser.add_subparsers(dest="command", required=True, metavar="COMMAND"), COMMANDS)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run one verb; its return value is the exit code (argparse exits 2 on a usage error itself)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted; finished frames are kept and a rerun resumes", file=sys.stderr)
        return 130
    except (ValueError, OSError, RuntimeError) as exc:  # readable one-line errors, no traceback
        print(f"omnigen {args.command}: error: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
