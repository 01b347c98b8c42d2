"""Checkpoints scored side by side on one split, as make validate scores its model.

    .venv/bin/python benchmarks/compare_checkpoints.py runs/validate/uov \
        runs/validate/runs/n-p2/last.pt runs/validate/runs/n-p2/crop.pt [--split test] [--by-class] [--out F]

Why: `omnigen train-crop` writes a detector's checkpoint with its crop stage trained apart; its
every other tensor is the detector's, so both predict the same boxes and what differs is what the
stage does (corners, front, the classes it rescores by). This predicts the split with each
checkpoint as validate's predict stage does (every class above the floor an anchor, EVAL_CONF,
EVAL_MAX_DET) and scores it as `omnigen eval` does, on one opened dataset. Any checkpoints may be
compared so (two runs of the detector, say); the first is the reference of the last line.

Prints a table (synthetic, or overall, then each view; with --by-class each class) of mAP50:95,
AP50, adherence and the corner errors, and last
`compare_checkpoints: NAME mAP50:95 X (REF Y), corner error rel A (B), adherence C deg (D)` for
each checkpoint after the first.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.bench_learning import rows_of  # noqa: E402
from benchmarks.crop_stage_ablation import COLUMNS, cell  # noqa: E402
from omnigen.files import atomic_write_json  # noqa: E402


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path, help="a merged UrbanOmniView dataset")
    ap.add_argument("weights", type=Path, nargs="+", help="checkpoints; the first is the reference")
    ap.add_argument("--split", default="test", help="the split scored ('all': every frame)")
    ap.add_argument("--imgsz", type=int, default=None, help="input size (default: each checkpoint's training size)")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--device", default=None)
    ap.add_argument("--by-class", action="store_true", help="add a row per class")
    ap.add_argument("--out", type=Path, default=None, help="write every row as JSON here")
    return ap.parse_args(argv)


def score(weights: Path, dataset: Path, split: str | None, imgsz: int | None, batch: int, device: str | None,
          by_class: bool, ds) -> tuple[dict, int]:
    """The checkpoint's rows (bench_learning.rows_of) on the split, and its number of detections."""
    from omnigen.detector.checkpoint import checkpoint_taxonomy
    from omnigen.detector.oks_eval import evaluate
    from omnigen.detector.predict import EVAL_MULTI_LABEL, load_for_prediction, predict_split

    model, state = load_for_prediction(weights, device)
    preds = predict_split(model, state, dataset, split, imgsz, batch, multi_label=EVAL_MULTI_LABEL,
                          vertical="off")  # the stages' own corners, as the rows written down before the snap
    return rows_of(evaluate(ds, preds, split=split, taxonomy=checkpoint_taxonomy(state)), by_class), len(preds)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from omnigen.dataset import Dataset

    if len(set(args.weights)) != len(args.weights):
        raise SystemExit("compare_checkpoints: a checkpoint is named twice")
    ds = Dataset.open(args.dataset, show_progress=False)
    split = None if args.split == "all" else args.split
    scored = {}
    for w in args.weights:
        scored[w], n = score(w, args.dataset, split, args.imgsz, args.batch, args.device, args.by_class, ds)
        print(f"{w}: {n} detections", flush=True)
    print("| rows | checkpoint | " + " | ".join(title for _, title, _ in COLUMNS) + " |")
    print("|---|---|" + "---|" * len(COLUMNS))
    keys = list(dict.fromkeys(k for rows in scored.values() for k in rows))  # a row one checkpoint lacks: '-'
    for key in keys:
        for w, rows in scored.items():
            print(f"| {key} | {w} | " + " | ".join(cell(rows.get(key, {}).get(f), d) for f, _, d in COLUMNS) + " |")
    if args.out:
        atomic_write_json(args.out, {"dataset": str(args.dataset), "split": args.split,
                                     "rows": {str(w): rows for w, rows in scored.items()}}, indent=1)
    ref = scored[args.weights[0]]
    main_key = next(iter(ref))
    for w in args.weights[1:]:
        r, b = scored[w][main_key], ref[main_key]
        print(f"compare_checkpoints: {w} mAP50:95 {cell(r['oks_map50_95'], 3)} ({args.weights[0]} "
              f"{cell(b['oks_map50_95'], 3)}), corner error rel {cell(r['corner_error_rel'], 3)} "
              f"({cell(b['corner_error_rel'], 3)}), adherence {cell(r['ground_adherence_deg'], 2)} deg "
              f"({cell(b['ground_adherence_deg'], 2)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
