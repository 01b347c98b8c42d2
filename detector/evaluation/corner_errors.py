"""How far predicted corners lie from the true ones, for objects matched by their 2D boxes.

OKS mAP says how many predictions are good enough at each threshold; it does not say how far
off the corners are, nor whether they are better than what the 2D box alone implies (the box
template baseline, detector/evaluation/box_template.py). These numbers do.

- Matching is by **2D box IoU >= 0.5**, not by OKS: ground truth and predictions of the same class
  in the same image, greedy by score (each prediction, best first, takes the unmatched object it
  overlaps most), one prediction per object, at most MAX_DETS predictions an image, as COCO's box
  evaluation matches. Matching by OKS would keep only the predictions whose corners are already
  close to the truth, so their error would be small by construction; matching by box measures the
  corners of every object the detector found, good or bad. The prediction's box is its `bbox`
  (x, y, w, h, what omnigen.detector.prediction.predict writes); a prediction without one is matched by its corners'
  extent clipped to the image.
- Errors are measured on the object's **labelled corners**, the ones OKS uses: in the image and
  in front of the camera (v > 0). `corner_error_px` is the median over every such corner of the
  group's matched objects of the Euclidean distance in pixels; `corner_error_rel` the median of
  the same distances each divided by sqrt(area of the object's 2D box), the scale OKS uses, so
  that a drone's 15-pixel cars and an ego camera's 200-pixel ones compare. Medians, because a
  few objects predicted turned 180 degrees would dominate a mean.
- Per corner (0..7, the contract's corner order), the same medians over that corner alone.
- `corner_spread`: the median over matched objects of how far the predicted corners spread about
  their centroid, as a fraction of the true corners' spread (root-mean-square distance to the
  centroid, over the object's labelled corners, at least three). 1 is a layout of the right size;
  well under 1 is a collapsed one, what a model predicts when it averages over layouts it cannot
  tell apart (a car's front and back), so the errors say how far off, this says in what way.
- `layout_error_rel`: corner_error_rel with the heading forgiven: per object the corners are
  compared as labelled or turned 180 degrees (TURN_IDX), whichever fits better (mean over its
  labelled corners). The same cuboid turned 180 degrees projects to the same eight points, so this
  says how well the layout (where the corners are) was learned apart from the heading (which one
  is the front); the gap to corner_error_rel is what wrong headings cost.

Everything after the matching is numpy over all matched objects at once.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from omnigen.conventions import NUM_KEYPOINTS, TURN_IDX

BOX_MATCH_IOU = 0.5


@dataclass
class CornerErrors:
    """The corner errors of one group of box-matched objects (NaN where none has a labelled corner)."""

    px: float
    rel: float
    objects: int  # matched objects with at least one labelled corner
    per_corner_px: list[float]
    per_corner_rel: list[float]
    spread: float = math.nan  # median predicted / true corner spread (module docstring)
    layout_rel: float = math.nan  # corner_error_rel up to the 180-degree turn (module docstring)

    @classmethod
    def none(cls) -> "CornerErrors":
        """A group without box-matched objects."""
        return cls(math.nan, math.nan, 0, [math.nan] * NUM_KEYPOINTS, [math.nan] * NUM_KEYPOINTS)


@dataclass
class MatchedCorners:
    """One row per box-matched ground-truth object: which object, its errors per corner."""

    gt_index: np.ndarray  # (M,) positions in the ground-truth annotation list
    det_index: np.ndarray  # (M,) positions in the prediction list
    err_px: np.ndarray  # (M, 8) pixels; NaN where the corner is not labelled (v = 0)
    err_rel: np.ndarray  # (M, 8) err_px / sqrt(box area)
    spread: np.ndarray | None = None  # (M,) predicted / true corner spread; NaN under 3 labelled corners
    layout_rel: np.ndarray | None = None  # (M, 8) err_rel in the order (as labelled or turned) that fits better

    def summary(self, mask: np.ndarray | None = None) -> CornerErrors:
        """Medians over the rows `mask` selects (all rows when None)."""
        px = self.err_px if mask is None else self.err_px[mask]
        rel = self.err_rel if mask is None else self.err_rel[mask]
        spread = np.full(len(self.err_px), np.nan) if self.spread is None else self.spread
        layout = np.full_like(self.err_rel, np.nan) if self.layout_rel is None else self.layout_rel
        return CornerErrors(px=_median(px.ravel()), rel=_median(rel.ravel()),
                            objects=int(np.isfinite(px).any(axis=1).sum()),
                            per_corner_px=_column_medians(px), per_corner_rel=_column_medians(rel),
                            spread=_median(spread if mask is None else spread[mask]),
                            layout_rel=_median((layout if mask is None else layout[mask]).ravel()))


def _median(values: np.ndarray) -> float:
    v = values[np.isfinite(values)]
    return float(np.median(v)) if v.size else math.nan


def _column_medians(a: np.ndarray) -> list[float]:
    with warnings.catch_warnings():  # an all-NaN column (no labelled corner) is NaN, not a warning
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(a, axis=0).tolist()


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, M) IoU of xyxy boxes; 0 where the union is empty."""
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.clip(rb - lt, 0, None).prod(axis=2)
    area_a = np.clip(a[:, 2:] - a[:, :2], 0, None).prod(axis=1)
    area_b = np.clip(b[:, 2:] - b[:, :2], 0, None).prod(axis=1)
    union = area_a[:, None] + area_b[None, :] - inter
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(union > 0, inter / union, 0.0)


def match_boxes(gt_image: np.ndarray, gt_cat: np.ndarray, gt_box: np.ndarray, det_image: np.ndarray,
                det_cat: np.ndarray, det_score: np.ndarray, det_box: np.ndarray,
                iou_min: float = BOX_MATCH_IOU, max_dets: int | None = None) -> np.ndarray:
    """For each ground-truth object the index of its matched prediction, -1 where none.

    Greedy by score within each image over all classes at once (IoU across classes is zeroed);
    ties in score keep the input order. Only the loop over an image's candidate predictions is
    Python, and it skips predictions that overlap no object of their class enough.
    """
    match = np.full(len(gt_image), -1, dtype=np.int64)
    if not len(gt_image) or not len(det_image):
        return match
    d_order = np.lexsort((-det_score, det_image))  # by image, then score descending (stable)
    g_order = np.argsort(gt_image, kind="stable")
    d_img, g_img = det_image[d_order], gt_image[g_order]
    images = np.intersect1d(d_img, g_img)
    d_lo, d_hi = np.searchsorted(d_img, images, "left"), np.searchsorted(d_img, images, "right")
    g_lo, g_hi = np.searchsorted(g_img, images, "left"), np.searchsorted(g_img, images, "right")
    for dl, dh, gl, gh in zip(d_lo.tolist(), d_hi.tolist(), g_lo.tolist(), g_hi.tolist()):
        if max_dets is not None:
            dh = min(dh, dl + max_dets)
        dets, gts = d_order[dl:dh], g_order[gl:gh]
        iou = box_iou(det_box[dets], gt_box[gts])
        iou[det_cat[dets][:, None] != gt_cat[gts][None, :]] = 0.0
        for r in np.flatnonzero(iou.max(axis=1) >= iou_min).tolist():
            row = iou[r]
            best = int(np.argmax(row))
            if row[best] < iou_min:  # everything it overlapped enough was taken
                continue
            match[gts[best]] = dets[r]
            iou[:, best] = -1.0  # taken
    return match


def matched_corners(gt_anns: Sequence[dict[str, Any]], det_anns: Sequence[dict[str, Any]],
                    det_boxes: np.ndarray, iou_min: float = BOX_MATCH_IOU,
                    max_dets: int | None = None) -> MatchedCorners:
    """Box-match COCO ground truth (bbox xywh, area, keypoints with v) and predictions (keypoints,
    score, category_id, image_id; boxes xyxy given apart), and measure their corner errors."""
    n_gt = len(gt_anns)
    gt_image = np.fromiter((a["image_id"] for a in gt_anns), np.int64, n_gt)
    gt_cat = np.fromiter((a["category_id"] for a in gt_anns), np.int64, n_gt)
    gt_box = np.asarray([a["bbox"] for a in gt_anns], dtype=np.float64).reshape(n_gt, 4)
    gt_box[:, 2:] += gt_box[:, :2]
    n_dt = len(det_anns)
    det_image = np.fromiter((a["image_id"] for a in det_anns), np.int64, n_dt)
    det_cat = np.fromiter((a["category_id"] for a in det_anns), np.int64, n_dt)
    det_score = np.fromiter((a["score"] for a in det_anns), np.float64, n_dt)
    match = match_boxes(gt_image, gt_cat, gt_box, det_image, det_cat, det_score,
                        np.asarray(det_boxes, dtype=np.float64).reshape(n_dt, 4), iou_min, max_dets)
    gi = np.flatnonzero(match >= 0)
    di = match[gi]
    gt_kp = np.asarray([gt_anns[i]["keypoints"] for i in gi.tolist()], dtype=np.float64).reshape(len(gi), NUM_KEYPOINTS, 3)
    dt_kp = np.asarray([det_anns[i]["keypoints"] for i in di.tolist()], dtype=np.float64).reshape(len(gi), NUM_KEYPOINTS, 3)
    err = np.hypot(*np.moveaxis(dt_kp[:, :, :2] - gt_kp[:, :, :2], 2, 0))
    err[gt_kp[:, :, 2] <= 0] = np.nan  # not labelled: outside the image or behind the camera
    area = np.fromiter((gt_anns[i]["area"] for i in gi.tolist()), np.float64, len(gi))
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(area > 0, np.sqrt(np.clip(area, 0, None)), np.nan)
    err_turned = np.hypot(*np.moveaxis(dt_kp[:, list(TURN_IDX), :2] - gt_kp[:, :, :2], 2, 0))
    err_turned[gt_kp[:, :, 2] <= 0] = np.nan
    with warnings.catch_warnings():  # an object without labelled corners: NaN either way
        warnings.simplefilter("ignore", RuntimeWarning)
        turned = np.nanmean(err_turned, axis=1) < np.nanmean(err, axis=1)
    layout = np.where(turned[:, None], err_turned, err)
    return MatchedCorners(gt_index=gi, det_index=di, err_px=err, err_rel=err / scale[:, None],
                          spread=spread_ratio(dt_kp[:, :, :2], gt_kp[:, :, :2], gt_kp[:, :, 2] > 0),
                          layout_rel=layout / scale[:, None])


def spread_ratio(pred: np.ndarray, gt: np.ndarray, labelled: np.ndarray) -> np.ndarray:
    """(M,) RMS distance of the predicted corners (M, 8, 2) to their centroid over the RMS distance
    of the true ones to theirs, both over each object's labelled corners (M, 8); NaN for objects with
    fewer than three (two points have no layout to speak of) or a true spread of zero."""
    w = labelled.astype(np.float64)[..., None]
    n = w.sum(1)  # (M, 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        def rms(xy: np.ndarray) -> np.ndarray:
            centre = (xy * w).sum(1) / n
            return np.sqrt((((xy - centre[:, None]) ** 2) * w).sum((1, 2)) / n[:, 0])
        truth = rms(gt)
        ratio = rms(pred) / np.where(truth > 0, truth, np.nan)
    return np.where(n[:, 0] >= 3, ratio, np.nan)


def corners_extent_boxes(keypoints: np.ndarray, width: np.ndarray, height: np.ndarray) -> np.ndarray:
    """(N, 4) xyxy: the extent of each prediction's corners (N, 8, >= 2), clipped to its image."""
    lo, hi = keypoints[:, :, :2].min(axis=1), keypoints[:, :, :2].max(axis=1)
    size = np.stack([width, height], axis=1).astype(np.float64)
    return np.concatenate([np.clip(lo, 0, size), np.clip(hi, 0, size)], axis=1)
