"""Keypoint metrics of a checkpoint or a predictions file: overall, per source, view, class and size.

    omnigen eval WEIGHTS_OR_PREDICTIONS DATASET [--split test] [--out FILE.json] [--taxonomy fine]
                 [--imgsz SIZE] [--batch 8] [--no-adherence] [--no-sizes]

A .json argument is a list of predictions in COCO-results form (image_id or frame_id,
category_id, keypoints: 24 numbers, score); a .pt argument is a checkpoint, run first over the
split by detector.predict. The metrics and their choices are documented in detector.oks_eval.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

import orjson

from omnigen.files import atomic_write_bytes


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("predictions", type=Path, metavar="WEIGHTS_OR_PREDICTIONS",
                   help="a checkpoint (.pt) or predictions in COCO-results form (.json)")
    p.add_argument("dataset", type=Path, metavar="DATASET")
    p.add_argument("--split", default="test", help="split to evaluate; 'all' for every frame (default: test)")
    p.add_argument("--out", type=Path, default=None, help="write the report as JSON here")
    p.add_argument("--taxonomy", default=None,
                   help="taxonomy of the predictions' category ids (preset or TOML; default: the checkpoint's, or fine)")
    p.add_argument("--imgsz", type=int, default=None,
                   help="network input size, with a checkpoint (default: its training size)")
    p.add_argument("--batch", type=int, default=8, help="images per batch, with a checkpoint")
    p.add_argument("--no-adherence", action="store_true", help="skip the ground-plane adherence (no 3D lifting)")
    p.add_argument("--no-sizes", action="store_true",
                   help="skip the rows per object size (a second COCOeval pass, reusing the first one's OKS)")


def load_predictions(path: Path) -> list[dict[str, Any]]:
    """A predictions file; unreadable or non-list content is an error naming the file."""
    from detector.results_file import read_results

    return read_results(path)


def _cell(v: float) -> float | str:
    """Undefined metrics (no ground truth, no matched prediction with a known ground plane) show as '-'."""
    return "-" if math.isnan(v) else v


def run(args: argparse.Namespace) -> int:
    from detector.oks_eval import evaluate
    from omnigen.dataset import Dataset, DatasetError
    from omnigen.progress import print_table
    from omnigen.taxonomy import load_taxonomy

    start = time.perf_counter()
    split = None if args.split in (None, "all") else args.split
    try:
        taxonomy = load_taxonomy(args.taxonomy or "fine")
        ds = Dataset.open(args.dataset)
        suffix = args.predictions.suffix.lower()
        if suffix == ".json":
            predictions = load_predictions(args.predictions)
        elif suffix == ".pt":
            if not args.predictions.exists():
                raise ValueError(f"{args.predictions}: no such checkpoint")
            from detector.checkpoint import checkpoint_taxonomy, load_checkpoint
            from detector.predict import predict_dataset

            if args.taxonomy is None:  # the classes the model was trained on
                taxonomy = checkpoint_taxonomy(load_checkpoint(args.predictions))

            predictions = predict_dataset(args.predictions, args.dataset, split=split, imgsz=args.imgsz,
                                          batch=args.batch)
        else:
            raise ValueError(f"{args.predictions}: expected weights (.pt) or predictions (.json)")
        report = evaluate(ds, predictions, split=split, taxonomy=taxonomy, adherence=not args.no_adherence,
                          source=str(args.predictions), sizes=not args.no_sizes)
    except (ValueError, KeyError, DatasetError, OSError) as exc:
        print(f"omnigen eval: {exc}", file=sys.stderr)
        return 2
    wall = time.perf_counter() - start

    print_table(
        f"omnigen eval: {args.predictions.name} on {args.dataset} ({args.split}). mAP: OKS 0.50:0.95, sigma "
        f"{report.oks_sigma}, maxDets {report.max_dets}; P/R/F1 at OKS 0.5 and the best-F1 conf; adh°: mean "
        f"ground-plane adherence of matched predictions",
        ["group", "imgs", "objs", "mAP", "AP50", "P", "R", "F1", "conf", "adh°"],
        [[r.group, r.images, r.objects, *(_cell(v) for v in (r.oks_map50_95, r.ap_oks50, r.precision, r.recall,
                                                              r.f1, r.conf_threshold, r.ground_adherence_deg))]
         for r in report.rows])
    for note in report.notes:
        print(f"note: {note}")
    if args.out is not None:
        doc = {"report": report.to_dict(),
               "arguments": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()
                             if k not in ("func", "command")},
               "wall_s": round(wall, 3)}
        atomic_write_bytes(args.out, orjson.dumps(doc, option=orjson.OPT_INDENT_2) + b"\n")
        print(f"wrote {args.out} ({wall:.1f} s)")
    return 0
