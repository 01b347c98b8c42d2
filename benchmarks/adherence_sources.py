"""Where a model's ground-plane adherence comes from: its corners with one part replaced, each
lifted and measured as `omnigen eval` does.

    .venv/bin/python benchmarks/adherence_sources.py runs/validate/uov \
        runs/validate/runs/n-p2/test-predictions.json [--split test] [--score-thr 0.3] [--out F]

Why: the adherence (docs/metric-3d.md) lifts each OKS-matched prediction with its class's median
size and K, and takes the mean angle between the lifted box's bottom edges and the frame's ground
plane. A model's corners can be off in many ways that the one figure does not tell apart. This
script keeps the model's matches (the same matching as eval, at OKS 0.5) and changes one thing
about the matched corners at a time, then lifts and measures them again
(`oks_eval.adherence_per_detection`, unchanged):

- `as predicted`: the model's corners, the figure eval prints;
- `vertical edges to the fitted vanishing point`: each of the four vertical edges (corner i to
  i + 4) turned about its midpoint, its length kept, to point at the image's vertical vanishing
  point, fitted from the image's own detections scored `--score-thr` or more (no truth, no K:
  what a calibration-free post-processing could do; `fit_vertical_vanishing_point`);
- `vertical edges to the true vanishing point`: the same, to the point K n the frame's true
  ground normal n projects to (an upper bound for any such fit);
- `true face shapes`: the top and the bottom face each given the truth's shape about the
  predicted face's centre (the faces' placement the model's, their layout the truth's);
- `true vertical offset`: the bottom face moved so that its centre lies the truth's offset from
  the top face's centre (the faces' shapes the model's);
- `true corners`: the truth's (eval's floor: the prior size is not the object's).

The truth replaces an object's corners only where all eight of its corners are defined. Prints a
table of the mean adherence (and the median) over the matches with a known ground plane, whole
and per view, and last `adherence_sources: as predicted X deg; fitted vanishing point Y; true
vanishing point Z; true face shapes A; true vertical offset B; true corners C`.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from pathlib import Path
from typing import Callable

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from omnigen.conventions import NUM_KEYPOINTS  # noqa: E402

from omnigen.detector.vanishing import (BOTTOM, TOP, distinct_rows, fit_vertical_vanishing_point,  # noqa: E402
                                        turn_vertical_edges)


def true_vanishing_point(K: np.ndarray, plane: np.ndarray, width: float, height: float) -> np.ndarray:
    """The unit homogeneous point, in vanishing.to_normalised coordinates, that the ground normal
    of `plane` ([n, d], camera frame) projects to through K: where every upright edge of the frame
    points."""
    v = np.asarray(K, dtype=np.float64) @ np.asarray(plane, dtype=np.float64)[:3]
    scale, (cx, cy) = max(width, height), ((width - 1) / 2, (height - 1) / 2)
    v = np.array([(v[0] - cx * v[2]) / scale, (v[1] - cy * v[2]) / scale, v[2]])
    return v / np.linalg.norm(v)


def true_face_shapes(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Each face (top, bottom) the truth's shape about the predicted face's centre; (8, 2)."""
    out = pred.copy()
    for face in (TOP, BOTTOM):
        out[face] = pred[face].mean(0) + true[face] - true[face].mean(0)
    return out


def true_vertical_offset(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """The bottom face moved so that its centre is the truth's offset from the top face's; (8, 2)."""
    out = pred.copy()
    want = true[BOTTOM].mean(0) - true[TOP].mean(0)
    out[BOTTOM] += want - (pred[BOTTOM].mean(0) - pred[TOP].mean(0))
    return out


PER_OBJECT: dict[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] = {
    "true face shapes": true_face_shapes,
    "true vertical offset": true_vertical_offset,
    "true corners": lambda pred, true: true.copy(),
}
VANISHING = ("vertical edges to the fitted vanishing point", "vertical edges to the true vanishing point")


def variant_keypoints(ds, m, score_thr: float) -> dict[str, dict[int, np.ndarray]]:
    """detection id -> its corners (8, 2) under each variant but `as predicted`, for the matched
    detections (the truth's where all eight corners are defined)."""
    matches = m.matches().matched_ids()
    anns, gt = m.anns, m.gt
    frame_of = {im["id"]: ds.index_of(im["frame_id"]) for im in m.gt_dict["images"]}
    out: dict[str, dict[int, np.ndarray]] = {name: {} for name in (*VANISHING, *PER_OBJECT)}
    by_image: dict[int, list[int]] = defaultdict(list)
    for i, a in enumerate(anns):
        by_image[a["image_id"]].append(i + 1)
    for image_id, dets in by_image.items():
        f = frame_of[image_id]
        w, h = float(ds.table.width[f]), float(ds.table.height[f])
        kp = np.asarray([anns[d - 1]["keypoints"] for d in dets], dtype=np.float64).reshape(len(dets), NUM_KEYPOINTS, 3)
        kp = kp[..., :2]
        matched = [k for k, d in enumerate(dets) if d in matches]
        if not matched:
            continue
        score = np.asarray([anns[d - 1]["score"] for d in dets])
        # multi-label prediction repeats a box with its corners once per class: fit each box once
        keep = distinct_rows(kp, np.flatnonzero(score >= score_thr))
        plane = ds.table.ground_plane[f]
        points = {VANISHING[0]: fit_vertical_vanishing_point(kp[keep], score[keep], w, h) if len(keep) else None,
                  VANISHING[1]: true_vanishing_point(ds.table.K[f], plane, w, h)
                  if np.isfinite(plane).all() else None}
        for name, v in points.items():
            if v is not None:
                turned = turn_vertical_edges(kp[matched], v, w, h)
                out[name].update({dets[k]: turned[j] for j, k in enumerate(matched)})
        for k in matched:
            truth = np.asarray(gt.anns[matches[dets[k]]]["keypoints"], dtype=np.float64).reshape(NUM_KEYPOINTS, 3)
            if (truth[:, 2] > 0).all():
                for name, fn in PER_OBJECT.items():
                    out[name][dets[k]] = fn(kp[k], truth[:, :2])
    return out


def adherence_table(ds, predictions: list[dict], split: str | None, score_thr: float, taxonomy: str = "fine"
                    ) -> dict[str, dict[str, dict[str, float]]]:
    """variant -> group ('overall' and 'view=...') -> {mean, median, objects} of the matched
    detections' adherence in degrees."""
    from omnigen.detector.oks_eval import adherence_per_detection, match_predictions

    m = match_predictions(ds, predictions, split, taxonomy)
    matches = m.matches().matched_ids()
    view_of = {im["id"]: im["view"] for im in m.gt_dict["images"]}
    variants = {"as predicted": {}, **variant_keypoints(ds, m, score_thr)}
    table: dict[str, dict[str, dict[str, float]]] = {}
    for name, replaced in variants.items():
        anns = [dict(a) for a in m.anns]
        for d, kp in replaced.items():
            kps = np.asarray(anns[d - 1]["keypoints"], dtype=np.float64).reshape(NUM_KEYPOINTS, 3).copy()
            kps[:, :2] = kp
            anns[d - 1]["keypoints"] = kps.ravel().tolist()
        angles, _, _ = adherence_per_detection(ds, m.gt, anns, matches)
        groups: dict[str, list[float]] = defaultdict(list)
        for d, a in angles.items():
            groups["overall"].append(a)
            groups[f"view={view_of[m.anns[d - 1]['image_id']]}"].append(a)
        table[name] = {g: {"mean": float(np.mean(v)), "median": float(np.median(v)), "objects": len(v)}
                       for g, v in sorted(groups.items())}
    return table


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path, help="a merged UrbanOmniView dataset")
    ap.add_argument("predictions", type=Path, help="COCO-results predictions (omnigen predict, validate's test-predictions.json)")
    ap.add_argument("--split", default="test", help="the split scored ('all': every frame)")
    ap.add_argument("--score-thr", type=float, default=0.3,
                    help="detections scored at least this fit each image's vertical vanishing point")
    ap.add_argument("--out", type=Path, default=None, help="write the table as JSON here")
    a = ap.parse_args(argv)
    from omnigen.dataset import Dataset
    from omnigen.files import atomic_write_json
    from omnigen.progress import print_table

    ds = Dataset.open(a.dataset, show_progress=False)
    try:
        predictions = json.loads(a.predictions.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise SystemExit(f"adherence_sources: {a.predictions}: {exc}") from None
    table = adherence_table(ds, predictions, None if a.split == "all" else a.split, a.score_thr)
    groups = list(dict.fromkeys(g for rows in table.values() for g in rows))
    print_table(f"ground-plane adherence (deg), mean (median) over the OKS-matched predictions: {a.predictions}",
                ["corners", *[f"{g} ({table['as predicted'].get(g, {}).get('objects', 0)})" for g in groups]],
                [(name, *[f"{r[g]['mean']:.2f} ({r[g]['median']:.2f})" if g in r else "-" for g in groups])
                 for name, r in table.items()])
    if a.out:
        atomic_write_json(a.out, {"dataset": str(a.dataset), "predictions": str(a.predictions), "split": a.split,
                                  "score_thr": a.score_thr, "adherence_deg": table}, indent=1)

    def mean(name: str) -> str:
        return f"{table[name]['overall']['mean']:.2f}" if "overall" in table[name] else "-"

    print(f"adherence_sources: as predicted {mean('as predicted')} deg; fitted vanishing point {mean(VANISHING[0])}; "
          f"true vanishing point {mean(VANISHING[1])}; true face shapes {mean('true face shapes')}; "
          f"true vertical offset {mean('true vertical offset')}; true corners {mean('true corners')}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
