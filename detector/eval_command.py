"""Keypoint metrics of a checkpoint or a predictions file: overall, per source, view, class and size.

    omnigen eval WEIGHTS_OR_PREDICTIONS DATASET [--split test] [--out FILE.json] [--taxonomy fine]
                 [--imgsz SIZE] [--batch 8] [--no-adherence] [--no-sizes] [--per-corner] [--baseline]

A .json argument is a list of predictions in COCO-results form (image_id or frame_id,
category_id, keypoints: 24 numbers, score, bbox); a .pt argument is a checkpoint, run first over the
split by omnigen.detector.prediction.predict. The metrics and their choices are documented in omnigen.detector.evaluation.oks_eval and
omnigen.detector.evaluation.corner_errors; `--baseline` also scores the box-template baseline (omnigen.detector.evaluation.box_template:
the same boxes, corners placed by the training split's mean layouts) and prints it beside the model.

`--out` is a new file or one eval wrote before (its first key is "omnigen": "eval"); the
predictions, the checkpoint and anything in the dataset folder are refused (omnigen.outputs).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import orjson

from omnigen.detector.predict_command import BATCH_MAX, IMGSZ_STEP, input_size
from omnigen.options import integer

if TYPE_CHECKING:
    from omnigen.detector.evaluation.oks_eval import EvalReport


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("predictions", type=Path, metavar="WEIGHTS_OR_PREDICTIONS",
                   help="a checkpoint (.pt) or predictions in COCO-results form (.json)")
    p.add_argument("dataset", type=Path, metavar="DATASET")
    p.add_argument("--split", default="test", help="split to evaluate; 'all' for every frame (default: test)")
    p.add_argument("--out", type=Path, default=None,
                   help="write the report as JSON here: a new file, or one eval wrote; never an input")
    p.add_argument("--taxonomy", default=None,
                   help="taxonomy of the predictions' category ids (preset or TOML; default: the checkpoint's, or fine)")
    p.add_argument("--imgsz", type=input_size, default=None,
                   help=f"network input size, a multiple of {IMGSZ_STEP}, with a checkpoint (default: its training size)")
    p.add_argument("--batch", type=integer(1, BATCH_MAX), default=8, help="images per batch, with a checkpoint")
    p.add_argument("--vertical", choices=("lines", "off"), default=None,
                   help="with a checkpoint: turn each image's vertical edges to its vertical vanishing point "
                        "(lines) or keep the network's corners (off) (default: the run's recipe, predict.vertical)")
    p.add_argument("--device", default=None, help="where a checkpoint predicts: cpu, cuda, cuda:1 (default: cuda when present)")
    p.add_argument("--single-label", action="store_true",
                   help="with a checkpoint, one class an anchor as `omnigen predict` gives (default: every class above "
                        "the 0.001 floor, as Ultralytics' validation scores)")
    p.add_argument("--no-adherence", action="store_true", help="skip the ground-plane adherence (no 3D lifting)")
    p.add_argument("--no-sizes", action="store_true",
                   help="skip the rows per object size (a second COCOeval pass, reusing the first one's OKS)")
    p.add_argument("--per-corner", action="store_true",
                   help="also the median corner errors per corner 0..7 (a table of the overall row's; all rows' in the JSON)")
    p.add_argument("--baseline", action="store_true",
                   help="also evaluate the box-template baseline (the predicted boxes with the training split's mean "
                        "corner layout per class and view); written under 'baseline' in the JSON")


def load_predictions(path: Path) -> list[dict[str, Any]]:
    """A predictions file; unreadable or non-list content is an error naming the file."""
    from omnigen.detector.prediction.results_file import read_results

    return read_results(path)


def _cell(v: float) -> float | str:
    """Undefined metrics (no ground truth, no matched prediction with a known ground plane) show as '-'."""
    return "-" if math.isnan(v) else v


def run(args: argparse.Namespace) -> int:
    from omnigen.detector.evaluation.box_template import evaluate_with_baseline, fit_box_template, training_frames
    from omnigen.detector.evaluation.oks_eval import evaluate
    from omnigen.dataset import Dataset, DatasetError
    from omnigen.outputs import check_output_file, json_made_by, write_output_file
    from omnigen.progress import print_table
    from omnigen.taxonomy import load_taxonomy

    if args.out is not None:  # before the work: a refused --out should not cost an evaluation
        check_output_file(args.out, "eval", json_made_by("eval"), inputs=[args.predictions, args.dataset])
    start = time.perf_counter()
    split = None if args.split in (None, "all") else args.split
    try:
        taxonomy = load_taxonomy(args.taxonomy or "fine")
        ds = Dataset.open(args.dataset)
        suffix = args.predictions.suffix.lower()
        if suffix == ".json":
            if args.single_label:
                raise ValueError(f"{args.predictions}: --single-label chooses how a checkpoint predicts; these "
                                 "predictions are made already")
            predictions = load_predictions(args.predictions)
        elif suffix == ".pt":
            if not args.predictions.exists():
                raise ValueError(f"{args.predictions}: no such checkpoint")
            from omnigen.detector.model.checkpoint import checkpoint_taxonomy
            from omnigen.detector.prediction.predict import load_for_prediction, predict_split

            model, state = load_for_prediction(args.predictions, args.device)
            if args.taxonomy is None:  # the classes the model was trained on
                taxonomy = checkpoint_taxonomy(state)
            predictions = predict_split(model, state, args.dataset, split=split, imgsz=args.imgsz, batch=args.batch,
                                        multi_label=not args.single_label, vertical=args.vertical)
        else:
            raise ValueError(f"{args.predictions}: expected weights (.pt) or predictions (.json)")
        options = dict(adherence=not args.no_adherence, source=str(args.predictions), sizes=not args.no_sizes,
                       per_corner=args.per_corner)
        template = baseline = None
        if args.baseline:
            frames, fitted_from = training_frames(ds)
            template = fit_box_template(ds, frames, taxonomy, fitted_from=fitted_from)
            report, baseline = evaluate_with_baseline(ds, predictions, split, taxonomy, template, **options)
        else:
            report = evaluate(ds, predictions, split=split, taxonomy=taxonomy, **options)
    except (ValueError, KeyError, DatasetError, OSError) as exc:
        print(f"omnigen eval: {exc}", file=sys.stderr)
        return 2
    wall = time.perf_counter() - start

    print_table(
        f"omnigen eval: {args.predictions.name} on {args.dataset} ({args.split}). mAP: OKS 0.50:0.95, sigma "
        f"{report.oks_sigma}, maxDets {report.max_dets}; P/R/F1 at OKS 0.5 and the best-F1 conf; adh°: mean "
        f"ground-plane adherence of matched predictions; err px / rel: median corner error of the objects matched "
        f"by box IoU >= {report.box_match_iou}, in pixels and / sqrt(box area); layout: err rel up to the 180° turn",
        ["group", "imgs", "objs", "mAP", "AP50", "P", "R", "F1", "conf", "adh°", "err px", "err rel", "layout"],
        [[r.group, r.images, r.objects, *(_cell(v) for v in (r.oks_map50_95, r.ap_oks50, r.precision, r.recall,
                                                              r.f1, r.conf_threshold, r.ground_adherence_deg,
                                                              r.corner_error_px, r.corner_error_rel,
                                                              r.layout_error_rel))]
         for r in report.rows])
    if args.per_corner:
        print_per_corner(report, baseline)
    if baseline is not None:
        print_comparison(report, baseline)
    for note in report.notes:
        print(f"note: {note}")
    for note in baseline.notes if baseline is not None else []:
        print(f"note (baseline): {note}")
    if args.out is not None:
        doc = {"omnigen": "eval",  # first: the mark a rerun recognises its own file by (omnigen.outputs.json_made_by)
               "report": report.to_dict(),
               "arguments": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()
                             if k not in ("func", "command")},
               "wall_s": round(wall, 3)}
        if baseline is not None:
            doc["baseline"] = baseline.to_dict()
            doc["baseline_template"] = template.to_dict()
        write_output_file(args.out, orjson.dumps(doc, option=orjson.OPT_INDENT_2) + b"\n", "eval", json_made_by("eval"),
                          inputs=[args.predictions, args.dataset])
        print(f"wrote {args.out} ({wall:.1f} s)")
    return 0


COMPARED = (("mAP50:95", "oks_map50_95"), ("AP50", "ap_oks50"), ("adherence_deg", "ground_adherence_deg"),
            ("corner_error_px", "corner_error_px"), ("corner_error_rel", "corner_error_rel"),
            ("corner_spread", "corner_spread"), ("layout_error_rel", "layout_error_rel"))


def print_comparison(report: "EvalReport", baseline: "EvalReport") -> None:
    """The overall rows of the model and of the box-template baseline, metric by metric."""
    from omnigen.progress import print_table

    m, b = report.row("overall"), baseline.row("overall")
    print_table("model vs box-template baseline (overall; the model's corners must beat the baseline's)",
                ["metric", "model", "baseline"],
                [[label, _cell(getattr(m, name)), _cell(getattr(b, name))] for label, name in COMPARED])


def print_per_corner(report: "EvalReport", baseline: "EvalReport | None") -> None:
    """Median corner errors per corner 0..7 of the overall row (the baseline's too, when evaluated)."""
    from omnigen.progress import print_table

    rows = []
    for who, r in (("model", report), ("baseline", baseline)):
        if r is None:
            continue
        o = r.row("overall")
        rows.append([f"{who} px", *(_cell(v) for v in o.corner_errors_per_corner)])
        rows.append([f"{who} rel", *(_cell(v) for v in o.corner_errors_rel_per_corner)])
    print_table("median corner error per corner (overall, box-matched objects)",
                ["", *(f"corner {i}" for i in range(len(rows[0]) - 1))], rows)
