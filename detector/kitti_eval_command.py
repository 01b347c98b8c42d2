"""KITTI AP (2D, BEV, 3D; R40 and R11) of KITTI label folders.

The numbers follow the official devkit (see omnigen.detector.evaluation.kitti_eval for every rule); the JSON holds
{"omnigen": "eval-kitti", "AP40": {class: {"bbox": [easy, moderate, hard], "bev": [...], "3d": [...]}},
"AP11": {...}} in percent. Its first key marks it as this command's: a rerun replaces it, any other
file at --out is refused (omnigen.outputs).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

JOB = "eval-kitti"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--gt", required=True, type=Path, help="folder of KITTI ground-truth labels (label_2)")
    p.add_argument("--pred", required=True, type=Path,
                   help="folder of KITTI-format predictions, one <id>.txt a frame with a 16th field, the score; "
                        "a missing file means no detections")
    p.add_argument("--out", type=Path, help="write the AP table as JSON here (a new file, or one eval-kitti wrote)")
    p.add_argument("--ids", type=Path, help="evaluate only these frame ids (one a line, as KITTI's val.txt); "
                                            "default: every .txt in --gt")


def run(args: argparse.Namespace) -> int:
    from omnigen.detector.evaluation.kitti_eval import CLASSES, DIFFICULTIES, METRICS, evaluate, read_folders, read_ids
    from omnigen.outputs import MARK_KEY, check_output_file, json_made_by, write_output_file
    from omnigen.progress import print_table

    for what, folder in (("--gt", args.gt), ("--pred", args.pred)):
        if not folder.is_dir():
            print(f"omnigen eval-kitti: {what} {folder} is not a folder", file=sys.stderr)
            return 2
    if args.ids is not None and not args.ids.is_file():
        print(f"omnigen eval-kitti: --ids {args.ids} not found", file=sys.stderr)
        return 2
    inputs = [args.gt, args.pred] + ([args.ids] if args.ids is not None else [])
    if args.out is not None:  # before the evaluation: a refused --out costs nothing
        check_output_file(args.out, JOB, json_made_by(JOB), inputs)
    start = time.perf_counter()
    ids, gts, preds = read_folders(args.gt, args.pred, read_ids(args.ids) if args.ids else None)
    result = evaluate(gts, preds, CLASSES)
    seconds = time.perf_counter() - start
    columns = ["class / box", *(d.capitalize() for d in DIFFICULTIES)]
    for kind in ("AP40", "AP11"):
        rows = [(f"{cls} {metric}", *result[kind][cls][metric]) for cls in CLASSES for metric in METRICS]
        print_table(f"KITTI {kind} (%): {len(ids):,} frames, {sum(len(p) for p in preds):,} detections "
                    f"({seconds:.1f} s)", columns, rows)
    if args.out is not None:
        write_output_file(args.out, (json.dumps({MARK_KEY: JOB, **result}, indent=2, allow_nan=False) + "\n").encode(),
                          JOB, json_made_by(JOB), inputs)
        print(f"wrote {args.out}")
    return 0
