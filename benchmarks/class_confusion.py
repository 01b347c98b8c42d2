"""Which class the detector gives each test object it finds: are rare classes missed, or named wrong?

Why: make validate's rarest classes (cyclists, tricyclists, barrows) score 0.000 OKS AP. That can
mean two different things with different cures: the detector draws no box on them (more examples,
more steps, a finer level), or it draws the box and names another class (a cyclist called a
pedestrian: a classification problem, where class-balanced losses and sampling act). Each test
object is matched, blind to the class, to the best-scoring prediction (score >= 0.2) whose 2D box
overlaps its own by IoU >= 0.5, as detector/corner_order.py matches; then its predicted class is
counted against its true one.

    .venv/bin/python benchmarks/class_confusion.py WEIGHTS DATASET [--split test] [--imgsz 640]
        [--batch 16] [--device cpu] [--min-score 0.2] [--out confusion.json]

Prints, per true class: test objects, found as itself, found as another class (and which most
often), not found; then, last,
`class confusion: found X of N objects, Y of them as another class; rare classes (under R
training instances) found A of B, C as another class`.
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from pathlib import Path
from typing import Any, Sequence

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omnigen.files import atomic_write_json  # noqa: E402

RARE = 130
"""Training instances under which a class counts as rare (make validate's five rarest classes)."""


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("weights", type=Path, help="a checkpoint (last.pt, best.pt)")
    ap.add_argument("dataset", type=Path, help="the dataset it is scored on (a merged UrbanOmniView folder)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--imgsz", type=int, default=None, help="input size (default: the training's)")
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--device", default=None)
    ap.add_argument("--min-score", type=float, default=0.2, help="predictions below this score are not matched")
    ap.add_argument("--min-iou", type=float, default=0.5)
    ap.add_argument("--out", type=Path, default=None, help="write the counts as JSON here")
    return ap.parse_args(argv)


def confusion(ds: Any, predictions: Sequence[dict[str, Any]], classes: list[str], class_of_fine: np.ndarray,
              frames: list[str], min_iou: float = 0.5, min_score: float = 0.2) -> dict[str, Counter]:
    """For each true class (taxonomy name), a Counter of what its test objects were matched as
    (corner_order.box_matches): a predicted class name, or None when no prediction matched. Objects
    of classes the taxonomy drops, and objects behind the camera, are left out (not targets)."""
    from omnigen.detector.corner_order import box_matches

    category = ds.objects.category
    out: dict[str, Counter] = {name: Counter() for name in classes}
    for r, p in box_matches(ds, predictions, frames, min_iou, min_score, keep=lambda r: class_of_fine[category[r]] >= 0):
        out[classes[int(class_of_fine[category[r]])]][None if p is None else classes[int(p["category_id"]) - 1]] += 1
    return out


def train_counts(dataset: Path, taxonomy: Any) -> dict[str, int]:
    """Training instances of each class (the train split), counted as class-balanced training counts them."""
    from omnigen.detector.balance import instance_counts
    from omnigen.detector.data import KeypointDataset, split_frames

    data = KeypointDataset(dataset, taxonomy, 32, split_frames(str(dataset), "train"))
    return dict(zip(taxonomy.classes, instance_counts(data.frame_classes(), len(taxonomy.classes)).tolist()))


def rows_of(table: dict[str, Counter], train: dict[str, int]) -> list[dict[str, Any]]:
    rows = []
    for name, seen in table.items():
        total = sum(seen.values())
        if not total:
            continue
        other = Counter({k: v for k, v in seen.items() if k not in (None, name)})
        top = other.most_common(1)[0] if other else None
        rows.append({"class": name, "train": train.get(name, 0), "objects": total, "as_itself": seen.get(name, 0),
                     "as_other": sum(other.values()), "top_other": top[0] if top else None,
                     "top_other_count": top[1] if top else 0, "not_found": seen.get(None, 0)})
    return rows


def summary(rows: list[dict[str, Any]], rare: int = RARE) -> str:
    found = sum(r["as_itself"] + r["as_other"] for r in rows)
    total = sum(r["objects"] for r in rows)
    other = sum(r["as_other"] for r in rows)
    few = [r for r in rows if r["train"] < rare]
    return (f"class confusion: found {found} of {total} objects, {other} of them as another class; rare classes "
            f"(under {rare} training instances) found {sum(r['as_itself'] + r['as_other'] for r in few)} of "
            f"{sum(r['objects'] for r in few)}, {sum(r['as_other'] for r in few)} as another class")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    from omnigen.dataset import Dataset
    from omnigen.detector.checkpoint import checkpoint_taxonomy
    from omnigen.detector.predict import load_for_prediction, predict_split
    from omnigen.splits import read_split

    model, state = load_for_prediction(args.weights, args.device)
    taxonomy = checkpoint_taxonomy(state)
    ds = Dataset.open(args.dataset, show_progress=False)
    preds = predict_split(model, state, args.dataset, split=args.split, imgsz=args.imgsz, batch=args.batch,
                          multi_label=False)  # the one class each detection was given
    classes, fine = taxonomy.classes, taxonomy.fine_class_ids()
    table = confusion(ds, preds, classes, fine, list(read_split(ds.root, args.split)), args.min_iou, args.min_score)
    rows = rows_of(table, train_counts(args.dataset, taxonomy))
    print(f"| class | training instances | {args.split} objects | found as itself | as another class (most often) "
          f"| not found |")
    print("|---|---|---|---|---|---|")
    for r in rows:
        top = f" ({r['top_other']} {r['top_other_count']})" if r["top_other"] else ""
        print(f"| {r['class']} | {r['train']} | {r['objects']} | {r['as_itself']} | {r['as_other']}{top} | {r['not_found']} |")
    line = summary(rows)
    if args.out:
        atomic_write_json(args.out, {"weights": str(args.weights), "dataset": str(args.dataset), "split": args.split,
                                     "min_score": args.min_score, "min_iou": args.min_iou, "rows": rows, "summary": line})
    print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
