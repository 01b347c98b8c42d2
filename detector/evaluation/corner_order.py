"""Which order of the eight corners fits a detector's predictions best: heading confusion.

OKS compares corner k of a prediction with corner k of the ground truth, so a box predicted in
the right place but turned 180 degrees (front and rear swapped, `TURN_IDX`) scores as badly as a
box in the wrong place. This module says how often that happens. Each ground-truth object of the
split (with no corner behind the camera) is matched to the highest-scoring prediction of the same
frame whose 2D box overlaps its own by IoU >= `min_iou` (box overlap, blind to the corners'
order); the mean corner distance is then computed under each candidate order and the object is
counted under the order that fits best (ties go to the first listed). A detector that learned headings is `as labelled` almost
always; one that guesses them splits between `as labelled` and `turned 180`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Iterator, Sequence

import numpy as np
import torch

from omnigen.conventions import FLIP_IDX, TURN_IDX
from omnigen.dataset import Dataset
from omnigen.detector.model.boxes import box_iou_pairwise
from omnigen.splits import read_split

ORDERS: dict[str, tuple[int, ...]] = {
    "as labelled": tuple(range(8)),
    "turned 180": TURN_IDX,
    "mirrored": FLIP_IDX,
    "turned +90": (1, 2, 3, 0, 5, 6, 7, 4),
    "turned -90": (3, 0, 1, 2, 7, 4, 5, 6),
}
"""Candidate orders: prediction corner ORDERS[k][i] is compared with ground-truth corner i."""


@dataclass
class CornerOrderCounts:
    matched: int  # ground-truth objects with a box-matched prediction
    unmatched: int
    best: dict[str, int]  # order name -> objects it fits best

    def fraction(self, name: str) -> float:
        return self.best[name] / self.matched if self.matched else float("nan")


def box_matches(ds: Dataset, predictions: Sequence[dict[str, Any]], frames: Sequence[str],
                min_iou: float = 0.5, min_score: float = 0.2,
                keep: Callable[[int], bool] | None = None) -> Iterator[tuple[int, dict[str, Any] | None]]:
    """Each object of the frames (none of its corners behind the camera, and `keep(row)` where given)
    as (object-table row, matched prediction or None): the highest-scoring prediction of the same
    frame with score >= `min_score` whose 2D box overlaps the object's by IoU >= `min_iou`, blind to
    its class and corners. `predictions` are COCO results with `frame_id`, `bbox` (x, y, w, h) and
    `score`, as `omnigen predict` and omnigen.detector.prediction.predict.predict_dataset write them."""
    by_frame: dict[str, list[dict[str, Any]]] = {}
    for p in predictions:
        if p["score"] >= min_score:
            by_frame.setdefault(str(p["frame_id"]), []).append(p)
    o = ds.objects
    for fid in frames:
        f = ds.index_of(fid)
        rows = [r for r in range(int(ds.offsets[f]), int(ds.offsets[f + 1]))
                if not o.behind_camera[r].any() and (keep is None or keep(r))]
        preds = by_frame.get(fid, [])
        if not preds:
            yield from ((r, None) for r in rows)
            continue
        scores = np.array([p["score"] for p in preds])
        boxes = np.array([[x, y, x + w, y + h] for x, y, w, h in (p["bbox"] for p in preds)], dtype=np.float64)
        iou = box_iou_pairwise(torch.from_numpy(o.bbox[rows].reshape(-1, 4)), torch.from_numpy(boxes)).numpy()  # (objects, preds)
        for n, r in enumerate(rows):
            ok = np.flatnonzero(iou[n] >= min_iou)
            yield r, (preds[int(ok[np.argmax(scores[ok])])] if len(ok) else None)


def corner_order_counts(ds: Dataset, predictions: Sequence[dict[str, Any]], split: str | None = "test",
                        min_iou: float = 0.5, min_score: float = 0.2) -> CornerOrderCounts:
    """Count, over the split's objects, the corner order that fits each one's matched prediction
    (box_matches)."""
    frames = read_split(ds.root, split) if split else list(ds.table.frame_id)
    o = ds.objects
    best = {name: 0 for name in ORDERS}
    matched = unmatched = 0
    for r, p in box_matches(ds, predictions, frames, min_iou, min_score):
        if p is None:
            unmatched += 1
            continue
        corners = np.asarray(p["keypoints"], dtype=np.float64).reshape(8, 3)[:, :2]
        err = {name: float(np.linalg.norm(corners[list(order)] - o.keypoints[r], axis=1).mean())
               for name, order in ORDERS.items()}
        best[min(err, key=err.get)] += 1
        matched += 1
    return CornerOrderCounts(matched, unmatched, best)
