"""The `omnigen` command: one entry point, short verbs, a summary table at the end.

Exit codes: 0 success; 1 the command ran and found problems (bad frames skipped, invalid dataset);
2 usage errors and commands that are not built yet.

The CLI sits on top of everything: it imports the parts (converters, scenes, detector) lazily,
inside the command that needs them, so `omnigen --help` stays fast and the parts never import it.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time
from pathlib import Path
from typing import Callable

from omnigen import __version__
from omnigen.files import LINK_MODES

NOT_BUILT = {
    "render": "rendering the procedural city (issue 6)",
    "stats": "the statistics report (issue 9)",
    "show": "the frame viewer (issue 9)",
    "train": "the bundled detector (issue 10)",
    "predict": "the bundled detector (issue 10)",
    "eval": "evaluation (issue 11)",
    "bev": "the BEV head (issue 11)",
}


EXPORTERS: dict[str, str] = {
    # format: module exposing add_arguments(parser) and run(args) -> int
    "kitti": "converters.kitti_export",
}


def _not_built(name: str) -> Callable[[argparse.Namespace], int]:
    def run(args: argparse.Namespace) -> int:
        print(f"omnigen {name}: not built yet: {NOT_BUILT[name]}.", file=sys.stderr)
        return 2
    return run


# ---------------------------------------------------------------------------------------------
# validate
# ---------------------------------------------------------------------------------------------


def _add_validate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("validate", help="check a dataset: schema, finite values, files present, unique ids")
    p.add_argument("dataset", type=Path)
    p.add_argument("--max-problems", type=int, default=50, help="how many problems to list (all are counted)")
    p.set_defaults(func=_run_validate)


def _run_validate(args: argparse.Namespace) -> int:
    from omnigen.checks import check_dataset
    from omnigen.progress import print_table

    start = time.perf_counter()
    n, problems = check_dataset(args.dataset)
    for p in problems[: args.max_problems]:
        print(f"  {p}")
    if len(problems) > args.max_problems:
        print(f"  ... and {len(problems) - args.max_problems} more")
    print_table(f"validate {args.dataset}", ["frames", "problems", "seconds"],
                [[n, len(problems), round(time.perf_counter() - start, 2)]])
    if problems:
        print(f"{args.dataset}: INVALID ({len(problems)} problems)")
        return 1
    print(f"{args.dataset}: valid")
    return 0


# ---------------------------------------------------------------------------------------------
# export
# ---------------------------------------------------------------------------------------------


def _add_export(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("export", help="write a dataset in another format (coco, yolo, kitti)")
    formats = p.add_subparsers(dest="format", required=True, metavar="FORMAT")
    coco = formats.add_parser("coco", help="COCO keypoints JSON (pycocotools reads it)")
    coco.add_argument("dataset", type=Path)
    coco.add_argument("--out", type=Path, required=True, help="output .json file")
    coco.add_argument("--split", default=None, help="only frames of this split (splits/<name>.txt)")
    coco.add_argument("--taxonomy", default=None, help="fine, coarse or a TOML file (default: the dataset's)")
    coco.set_defaults(func=_run_export_coco)
    yolo = formats.add_parser("yolo", help="Ultralytics pose layout (images/, labels/, data.yaml)")
    yolo.add_argument("dataset", type=Path)
    yolo.add_argument("--out", type=Path, required=True, help="output folder")
    yolo.add_argument("--taxonomy", default=None, help="fine, coarse or a TOML file (default: the dataset's)")
    yolo.add_argument("--link", choices=LINK_MODES, default="hardlink", help="how images are placed")
    yolo.set_defaults(func=_run_export_yolo)
    _add_plugins(formats, EXPORTERS, "export")


def _run_export_coco(args: argparse.Namespace) -> int:
    from omnigen.coco import export_coco
    from omnigen.dataset import Dataset
    from omnigen.progress import print_table
    from omnigen.taxonomy import load_taxonomy

    start = time.perf_counter()
    ds = Dataset.open(args.dataset)
    counts = export_coco(ds, args.out, args.split, _taxonomy_for(ds, args.taxonomy))
    print_table(f"export coco -> {args.out}", ["images", "annotations", "categories", "seconds"],
                [[counts["images"], counts["annotations"], counts["categories"], round(time.perf_counter() - start, 2)]])
    return 0


def _taxonomy_for(ds, name: str | None):
    """The taxonomy asked for, else the one the dataset's manifest records, else fine."""
    from omnigen.taxonomy import load_taxonomy

    return load_taxonomy(name or ds.manifest.get("taxonomy", {}).get("name", "fine"))


def _run_export_yolo(args: argparse.Namespace) -> int:
    from omnigen.dataset import Dataset
    from omnigen.progress import print_table
    from omnigen.yolo import export_yolo

    start = time.perf_counter()
    ds = Dataset.open(args.dataset)
    counts = export_yolo(ds, args.out, _taxonomy_for(ds, args.taxonomy), args.link)
    print_table(f"export yolo -> {args.out}", ["images", "objects", "classes", "seconds"],
                [[counts["images"], counts["objects"], counts["classes"], round(time.perf_counter() - start, 2)]])
    print(f"Ultralytics dataset YAML: {args.out / 'data.yaml'}")
    return 0


# ---------------------------------------------------------------------------------------------
# merge
# ---------------------------------------------------------------------------------------------


def _add_merge(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("merge", help="merge source datasets into UrbanOmniView with a held-out test split")
    p.add_argument("sources", type=Path, nargs="*", help="source datasets (render and convert outputs)")
    p.add_argument("--out", type=Path, required=True, help="output dataset folder")
    p.add_argument("--taxonomy", default="fine", help="fine, coarse or a TOML file; recorded in the manifest")
    p.add_argument("--test-fraction", type=float, default=0.10, help="share of each source and view held out")
    p.add_argument("--seed", type=int, default=0, help="seed of the test-split draw")
    p.add_argument("--split-file", type=Path, action="append", default=[],
                   help="a list of frame ids (or source ids such as KITTI's 000123); the file's stem names "
                        "the split; repeatable (e.g. train.txt and val.txt)")
    p.add_argument("--update", action="store_true", help="add sources to an existing merge, keeping its splits")
    p.add_argument("--link", choices=LINK_MODES, default="hardlink", help="how images are placed")
    p.set_defaults(func=_run_merge)


def _run_merge(args: argparse.Namespace) -> int:
    from omnigen.merge import merge
    from omnigen.progress import print_table
    from omnigen.taxonomy import load_taxonomy

    if not args.sources and not args.update:
        print("omnigen merge: give at least one source dataset", file=sys.stderr)
        return 2
    r = merge(args.sources, args.out, load_taxonomy(args.taxonomy), args.test_fraction, args.seed,
              args.split_file, args.update, args.link)
    print_table(f"merge -> {args.out}", ["source", "frames"], sorted(r.by_source.items()))
    print_table("splits", ["split", "frames"], sorted(r.by_split.items()))
    links = ", ".join(f"{k} {v}" for k, v in sorted(r.link_modes.items())) or "-"
    print_table("summary", ["frames", "objects", "unique images", "images placed", "seconds"],
                [[r.frames, r.objects, r.unique_images, links, round(r.seconds, 2)]])
    return 0


# ---------------------------------------------------------------------------------------------
# convert
# ---------------------------------------------------------------------------------------------


def _add_convert(sub: argparse._SubParsersAction) -> None:
    from converters import CONVERTERS

    p = sub.add_parser("convert", help="convert a public dataset (kitti, dair) into UrbanOmniView")
    names = p.add_subparsers(dest="converter", required=True, metavar="DATASET")
    _add_plugins(names, CONVERTERS, "convert")


def _add_plugins(subparsers: argparse._SubParsersAction, registry: dict[str, str], verb: str) -> None:
    """One subcommand per registry entry; the module gives add_arguments(parser) and run(args)."""
    for name, module_name in registry.items():
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name != module_name:
                raise
            q = subparsers.add_parser(name, help="(not built yet)")
            q.set_defaults(func=lambda args, n=name: _say_not_built(f"{verb} {n}"))
            continue
        q = subparsers.add_parser(name, help=(module.__doc__ or "").strip().splitlines()[0])
        module.add_arguments(q)
        q.set_defaults(func=module.run)


def _say_not_built(what: str) -> int:
    print(f"omnigen {what}: not built yet.", file=sys.stderr)
    return 2


# ---------------------------------------------------------------------------------------------
# main
# ---------------------------------------------------------------------------------------------


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="omnigen",
        description="Training data for calibration-free monocular 3D object detection in cities.",
    )
    parser.add_argument("--version", action="version", version=f"omnigen {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in ("render",):
        sub.add_parser(name, help=NOT_BUILT[name], add_help=False).set_defaults(func=_not_built(name))
    _add_convert(sub)
    _add_merge(sub)
    _add_export(sub)
    for name in ("stats", "show"):
        sub.add_parser(name, help=NOT_BUILT[name], add_help=False).set_defaults(func=_not_built(name))
    _add_validate(sub)
    for name in ("train", "predict", "eval", "bev"):
        sub.add_parser(name, help=NOT_BUILT[name], add_help=False).set_defaults(func=_not_built(name))
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra and args.command not in NOT_BUILT:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
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
