"""Write a dataset in another format (coco, yolo, kitti), or a model as ONNX.

COCO and YOLO are written here (the core's own formats); the other formats are command modules of
the parts, listed in the command registry's EXPORTERS (omnigen/cli.py), the one place the core
names a part.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from omnigen.files import LINK_MODES


def add_arguments(p: argparse.ArgumentParser) -> None:
    from omnigen import cli

    formats = p.add_subparsers(dest="format", required=True, metavar="FORMAT")
    coco = formats.add_parser("coco", help="COCO keypoints JSON (pycocotools reads it)", formatter_class=cli.HelpFormatter)
    coco.add_argument("dataset", type=Path)
    coco.add_argument("--out", type=Path, required=True,
                      help="output .json file (new, or one export coco wrote; never in the dataset)")
    coco.add_argument("--split", default=None, help="only frames of this split (splits/<name>.txt)")
    coco.add_argument("--taxonomy", default=None, help="fine, coarse or a TOML file (default: the dataset's)")
    yolo = formats.add_parser("yolo", help="Ultralytics pose layout (images/, labels/, data.yaml)",
                              formatter_class=cli.HelpFormatter)
    yolo.add_argument("dataset", type=Path)
    yolo.add_argument("--out", type=Path, required=True,
                      help="output folder (new, empty or an earlier export yolo; outside the dataset)")
    yolo.add_argument("--taxonomy", default=None, help="fine, coarse or a TOML file (default: the dataset's)")
    yolo.add_argument("--link", choices=LINK_MODES, default="hardlink", help="how images are placed")
    cli.add_commands(formats, cli.EXPORTERS)


def run(args: argparse.Namespace) -> int:
    """COCO and YOLO; a registered exporter's parser sets its own module's run, which argparse calls instead."""
    return {"coco": _run_coco, "yolo": _run_yolo}[args.format](args)


def _run_coco(args: argparse.Namespace) -> int:
    from omnigen.formats.coco import export_coco
    from omnigen.dataset import Dataset
    from omnigen.progress import print_table

    start = time.perf_counter()
    ds = Dataset.open(args.dataset)
    counts = export_coco(ds, args.out, args.split, _taxonomy_for(ds, args.taxonomy))
    print_table(f"export coco -> {args.out}", ["images", "annotations", "categories", "seconds"],
                [[counts["images"], counts["annotations"], counts["categories"], round(time.perf_counter() - start, 2)]])
    return 0


def _run_yolo(args: argparse.Namespace) -> int:
    from omnigen.dataset import Dataset
    from omnigen.progress import print_table
    from omnigen.formats.yolo import export_yolo

    start = time.perf_counter()
    ds = Dataset.open(args.dataset)
    counts = export_yolo(ds, args.out, _taxonomy_for(ds, args.taxonomy), args.link)
    print_table(f"export yolo -> {args.out}", ["images", "objects", "classes", "seconds"],
                [[counts["images"], counts["objects"], counts["classes"], round(time.perf_counter() - start, 2)]])
    print(f"Ultralytics dataset YAML: {args.out / 'data.yaml'}")
    return 0


def _taxonomy_for(ds, name: str | None):
    """The taxonomy asked for, else the one the dataset's manifest records, else fine."""
    from omnigen.taxonomy import load_taxonomy, recorded_taxonomy

    return load_taxonomy(name) if name else recorded_taxonomy(ds.manifest)
