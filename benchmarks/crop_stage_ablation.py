"""What the crop stage's corners add, at the same detections: a crop-stage checkpoint scored twice.

Why: a model trained with the crop stage (`train --heading-crop`) predicts each detection's corners
twice, once by its head and once from the detection's own crop, and prediction keeps the crop's.
Scored on its own, a run mixes what the stage does with everything else the recipe changed. Here
the same weights predict the same split with and without the stage (the loaded model's
`crop_net` set to None), so boxes, scores and matches are the same and only the corners differ, and both
are set beside the box-template baseline (corners from each box and the class's mean layout).
It answers, for instance, whether the stage is what moves the ground-plane adherence.

A stage that names classes (`train --crop-classes`) also rescores the detections it refines; a
third pass keeps its corners and the head's scores (`crop_classes=False`), so that what the
rescoring does to each class's AP is measured on the same weights too; and two more rescore by the
anchor's best class score instead of the detection's class's own, the second with every class of
each refined box (`crop_score_by` "object" and "every", crop_stage.SCORE_BY): whether the crop
should name the class alone.

    .venv/bin/python benchmarks/crop_stage_ablation.py WEIGHTS DATASET [--split test] [--imgsz 640]
        [--batch 16] [--device cpu] [--by-class] [--out ablation.json]

Prints a table per row (the synthetic rows, then each view, then with --by-class each class over
the whole split) and, last,
`crop stage: mAP50:95 X (head's corners Y), corner error rel A (head B, box template C),
adherence D deg (head E)`, and for a stage that names classes `; rescored by the crop's classes:
mAP50:95 X (the head's scores Z; scored by object W, scored by every V)`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.bench_learning import rows_of  # noqa: E402
from omnigen.files import atomic_write_json  # noqa: E402

OTHER_SCORE_BY = ("object", "every")
"""The crop_score_by modes scored beside prediction's default (crop_stage.SCORE_BY)."""
COLUMNS = (("oks_map50_95", "mAP50:95", 3), ("ap_oks50", "AP50", 3), ("ground_adherence_deg", "adherence (deg)", 2),
           ("corner_error_px", "corner error px", 2), ("corner_error_rel", "rel", 3))


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("weights", type=Path, help="a checkpoint trained with the crop stage (last.pt, best.pt)")
    ap.add_argument("dataset", type=Path, help="the dataset it is scored on (a merged UrbanOmniView folder)")
    ap.add_argument("--split", default="test", help="the split scored ('all': every frame)")
    ap.add_argument("--imgsz", type=int, default=None, help="input size (default: the training's)")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--device", default=None)
    ap.add_argument("--single-label", action="store_true",
                    help="score one class an anchor (as `omnigen predict` gives and as rows before 2026-11-27 were scored); default: every class above the floor, as omnigen eval")
    ap.add_argument("--by-class", action="store_true",
                    help="add a row per class (over the whole split, as omnigen eval's class rows): where a stage "
                         "that names classes moves AP")
    ap.add_argument("--out", type=Path, default=None, help="write every row as JSON here")
    return ap.parse_args(argv)


def same_boxes(a: list[dict[str, Any]], b: list[dict[str, Any]]) -> bool:
    """Whether two prediction lists hold the same detections' boxes and classes (in any order: a
    stage that rescores sorts again)."""
    def key(d: dict[str, Any]) -> tuple[Any, ...]:
        return (d["image_id"], d["category_id"], *d["bbox"])
    return sorted(map(key, a)) == sorted(map(key, b))


def score(args: argparse.Namespace) -> tuple[dict[str, Any], dict[str, Any], dict[str, Any], int,
                                             dict[str, Any] | None, dict[str, dict[str, Any]]]:
    """(crop-stage rows, head rows, box-template rows, detections, rows of the crop's corners with
    the head's scores or None, rows of each other `crop_score_by`, by it): the checkpoint's
    predictions with and without its crop stage (and, for a stage that names classes, without its
    rescoring and rescoring otherwise), scored on one opened dataset; the
    template scores the boxes once (they are the same every way)."""
    from omnigen.dataset import Dataset
    from omnigen.detector.box_template import evaluate_with_baseline
    from omnigen.detector.checkpoint import checkpoint_taxonomy
    from omnigen.detector.oks_eval import evaluate
    from omnigen.detector.predict import load_for_prediction, predict_split

    model, state = load_for_prediction(args.weights, args.device)
    if model.crop_net is None:
        raise SystemExit(f"crop_stage_ablation: {args.weights} has no crop stage (trained without --heading-crop)")
    split = None if args.split == "all" else args.split
    # vertical="off" throughout: the network's own corners, as the rows written down before the snap
    staged = predict_split(model, state, args.dataset, split, args.imgsz, args.batch, multi_label=not args.single_label, vertical="off")
    unscored, others = None, {}
    if model.crop_net.num_classes:  # the crop's corners, the head's scores; and rescored otherwise
        unscored = predict_split(model, state, args.dataset, split, args.imgsz, args.batch,
                                 multi_label=not args.single_label, vertical="off", crop_classes=False)
        others = {by: predict_split(model, state, args.dataset, split, args.imgsz, args.batch,
                                    multi_label=not args.single_label, vertical="off", crop_score_by=by) for by in OTHER_SCORE_BY}
    model.crop_net = None  # the head's own corners, the same detections
    plain = predict_split(model, state, args.dataset, split, args.imgsz, args.batch, multi_label=not args.single_label, vertical="off")
    # the stage's corners never move a box; its classes may rescore and (single-label) relabel and
    # drop detections, so for a stage that names classes the pass with the head's scores is compared
    if not same_boxes(staged if unscored is None else unscored, plain):
        raise SystemExit("crop_stage_ablation: the detections differ with and without the stage")
    ds = Dataset.open(args.dataset, show_progress=False)
    taxonomy = checkpoint_taxonomy(state)
    report, baseline = evaluate_with_baseline(ds, staged, split=split, taxonomy=taxonomy)
    head = evaluate(ds, plain, split=split, taxonomy=taxonomy)
    head_scores = None if unscored is None else rows_of(evaluate(ds, unscored, split=split, taxonomy=taxonomy),
                                                        args.by_class)
    other_rows = {by: rows_of(evaluate(ds, preds, split=split, taxonomy=taxonomy), args.by_class)
                  for by, preds in others.items()}
    return (rows_of(report, args.by_class), rows_of(head, args.by_class), rows_of(baseline, args.by_class),
            len(staged), head_scores, other_rows)


def cell(v: Any, digits: int) -> str:
    return "-" if v is None else f"{v:.{digits}f}"


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    stage, head, template, n_stage, head_scores, other_rows = score(args)
    print(f"{args.weights} on {args.dataset} ({args.split} split, {n_stage} detections): corners from the crop "
          "stage, from the head, and the box template's (the same detections each time)"
          + ("; the crop stage's corners with the head's scores (not rescored by the crop's classes)"
             if head_scores else ""))
    print("| rows | corners | " + " | ".join(title for _, title, _ in COLUMNS) + " |")
    print("|---|---|" + "---|" * len(COLUMNS))
    for key in stage:
        passes = [("crop stage", stage)] + ([("crop stage, head's scores", head_scores)] if head_scores else []) \
            + [(f"crop stage, scored by {by}", rows) for by, rows in other_rows.items()] \
            + [("head", head), ("box template", template)]
        for name, rows in passes:
            r = rows[key]
            print(f"| {key} | {name} | " + " | ".join(cell(r[f], d) for f, _, d in COLUMNS) + " |")
    main_key = next(iter(stage))
    s, h, t = stage[main_key], head[main_key], template[main_key]
    if args.out:
        atomic_write_json(args.out, {"weights": str(args.weights), "dataset": str(args.dataset), "split": args.split,
                                     "detections": n_stage, "crop_stage": stage, "head": head, "box_template": template,
                                     **({"crop_stage_head_scores": head_scores} if head_scores else {}),
                                     **{f"crop_stage_scored_by_{by}": rows for by, rows in other_rows.items()}},
                          indent=1)
    print(f"crop stage: mAP50:95 {cell(s['oks_map50_95'], 3)} (head's corners {cell(h['oks_map50_95'], 3)}), "
          f"corner error rel {cell(s['corner_error_rel'], 3)} (head {cell(h['corner_error_rel'], 3)}, box template "
          f"{cell(t['corner_error_rel'], 3)}), adherence {cell(s['ground_adherence_deg'], 2)} deg "
          f"(head {cell(h['ground_adherence_deg'], 2)})"
          + (f"; rescored by the crop's classes: mAP50:95 {cell(s['oks_map50_95'], 3)} (the head's scores "
             f"{cell(head_scores[main_key]['oks_map50_95'], 3)}; "
             + ", ".join(f"scored by {by} {cell(rows[main_key]['oks_map50_95'], 3)}" for by, rows in other_rows.items())
             + ")" if head_scores else ""))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
