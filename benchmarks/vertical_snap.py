"""What turning predicted vertical edges to the image's vertical vanishing point does, and how well
the point is found: `omnigen predict --vertical lines` measured against `--vertical off`.

    .venv/bin/python benchmarks/vertical_snap.py runs/validate/uov runs/validate/runs/n-p2/crop.pt \
        [--split train] [--frames 120] [--variant NAME:key=value,...] [--out F]

Why: the adherence (docs/metric-3d.md) is the tilt of boxes lifted from predicted corners, and a
box tilts most when its vertical edges miss the frame's vertical vanishing point
(benchmarks/adherence_sources.py). `omnigen predict` finds that point from the detections and
the image's line segments (detector/vanishing.py) and turns each detection's vertical edges to it.
This script predicts `--frames` frames of `--split` (evenly spaced through it) once, with the
corners as the network placed them, then applies each variant, on the frames' own images as
read from the dataset (prediction snaps on the letterboxed input less its padding: the same
pixels where the frames are square at the model's input size, as make validate's are), of vanishing.SnapOptions (the
default first: `default:`; others as NAME:key=value,... of its fields) and prints, per view:

- the point's error: the mean angle, over a 5 x 5 grid of image points, between the direction to
  the fitted point and to the true one (K n, n the frame's ground normal: truth, for scoring
  only), median and mean over the frames, for the detections' fit alone (`first`) and refined
  with the line segments;
- the ground-plane adherence, mean over the OKS-matched detections as `omnigen eval` computes it,
  with the corners as placed (`off`) and snapped;
- OKS mAP50:95 of each.

The defaults were chosen on make validate's train split (`--split train`), so that the test
split's figures in docs/RESULTS.md are not tuned on. Last line: `vertical_snap: adherence off X
deg, snapped Y; point error Z deg (first W), median over frames; mAP50:95 off A, snapped B`.
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from collections import defaultdict
from dataclasses import fields, replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

GRID = np.stack(np.meshgrid(np.linspace(-0.4, 0.4, 5), np.linspace(-0.4, 0.4, 5)), -1).reshape(-1, 2)


def point_error_deg(v: np.ndarray, truth: np.ndarray) -> float:
    """Mean angle (degrees) between the lines to two points from a grid over the image (a point
    near the image is judged where the vertical edges are, not by its distance)."""
    a, b = v[:2] - GRID * v[2], truth[:2] - GRID * truth[2]
    c = np.abs(np.sum(a * b, 1)) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-12)
    return float(np.degrees(np.arccos(np.clip(c, 0, 1))).mean())


def true_point(K: np.ndarray, plane: np.ndarray, width: float, height: float) -> np.ndarray:
    """The point the ground's downward direction projects to, in vanishing.to_normalised
    coordinates, signed as vanishing.py signs points (adherence_sources' point, whose sign is the
    upward normal's)."""
    from benchmarks.adherence_sources import true_vanishing_point

    return -true_vanishing_point(K, plane, width, height)


def parse_variant(text: str):
    """'NAME:key=value,...' -> (NAME, SnapOptions); a clear exit naming a bad key or value."""
    from omnigen.detector.vanishing import SnapOptions

    name, _, spec = text.partition(":")
    if not name:
        raise SystemExit(f"vertical_snap: --variant {text!r}: NAME:key=value,... (a name first)")
    types = {f.name: f.type for f in fields(SnapOptions)}
    values: dict[str, float | int] = {}
    for item in filter(None, spec.split(",")):
        key, eq, value = item.partition("=")
        if not eq or key not in types:
            raise SystemExit(f"vertical_snap: --variant {text!r}: {key!r} is not one of {', '.join(types)}")
        try:
            values[key] = int(value) if types[key] in (int, "int") else float(value)
        except ValueError:
            raise SystemExit(f"vertical_snap: --variant {text!r}: {key}={value!r} is not a number") from None
    return name, replace(SnapOptions(), **values)


def snapped(predictions: list[dict], gray_of, opts
            ) -> tuple[list[dict], dict[int, tuple[np.ndarray, np.ndarray]], list[float]]:
    """The predictions with each image's vertical edges turned (vanishing.snap_vertical's steps),
    image id -> (first point, refined point) where one was found, and the seconds each image's
    snap took (the image already decoded, as prediction has it)."""
    from omnigen.conventions import NUM_KEYPOINTS
    from omnigen.detector.vanishing import turn_vertical_edges, vertical_points

    out = copy.deepcopy(predictions)
    by_image: dict[int, list[int]] = defaultdict(list)
    for i, p in enumerate(predictions):
        by_image[p["image_id"]].append(i)
    points = {}
    seconds = []
    for image_id, idx in by_image.items():
        gray = gray_of(image_id)
        t0 = time.perf_counter()
        h, w = gray.shape[:2]
        kp = np.asarray([predictions[i]["keypoints"] for i in idx], dtype=np.float64).reshape(-1, NUM_KEYPOINTS, 3)
        scores = np.asarray([predictions[i]["score"] for i in idx], dtype=np.float64)
        found = vertical_points(gray, kp[..., :2], scores, opts)
        if found is None:
            continue
        first, v = found
        turned = turn_vertical_edges(kp[..., :2], v, w, h)
        seconds.append(time.perf_counter() - t0)
        points[image_id] = (first, v)
        for j, i in enumerate(idx):
            k = kp[j].copy()
            k[:, :2] = turned[j]
            out[i]["keypoints"] = k.ravel().tolist()
    return out, points, seconds


def adherence_and_map(ds, predictions: list[dict], frames: list[str]) -> tuple[dict[str, float], float]:
    """Mean adherence per view ('overall' too) over the OKS-matched detections, and OKS mAP50:95,
    on the frames predicted (a split of them alone)."""
    from omnigen.detector.oks_eval import (adherence_per_detection, ap_numbers, evalimgs_subset, match_predictions,
                                           run_quietly)

    m = match_predictions(ds, predictions, None)
    ids = {im["id"] for im in m.gt_dict["images"] if im["frame_id"] in set(frames)}
    _, sub = evalimgs_subset(m.e, ids)
    run_quietly(sub.accumulate)
    mean_ap = ap_numbers(sub.eval["precision"])[0]
    angles, _, _ = adherence_per_detection(ds, m.gt, m.anns, m.matches().matched_ids())
    view_of = {im["id"]: im["view"] for im in m.gt_dict["images"]}
    groups: dict[str, list[float]] = defaultdict(list)
    for d, a in angles.items():
        groups["overall"].append(a)
        groups[view_of[m.anns[d - 1]["image_id"]]].append(a)
    return {g: float(np.mean(v)) for g, v in groups.items()}, float(mean_ap)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", type=Path, help="a merged UrbanOmniView dataset with ground planes")
    ap.add_argument("weights", type=Path, help="a detector checkpoint (validate's crop.pt)")
    ap.add_argument("--split", default="train", help="the split whose frames are predicted ('all': every frame)")
    ap.add_argument("--frames", type=int, default=120, help="frames predicted, evenly spaced through the split")
    ap.add_argument("--variant", action="append", default=None, metavar="NAME:key=value,...",
                    help="vanishing.SnapOptions to compare (repeatable); the default is always first")
    ap.add_argument("--out", type=Path, default=None, help="write the figures as JSON here")
    a = ap.parse_args(argv)
    variants = [parse_variant("default:"), *[parse_variant(v) for v in a.variant or []]]
    if len({n for n, _ in variants}) != len(variants):
        raise SystemExit("vertical_snap: two variants share a name")

    import cv2

    from omnigen.dataset import Dataset
    from omnigen.detector.checkpoint import checkpoint_taxonomy
    from omnigen.detector.data import KeypointDataset, split_frames
    from omnigen.detector.predict import (EVAL_CONF, EVAL_MAX_DET, EVAL_MULTI_LABEL, PredictOptions,
                                          load_for_prediction, predict_frames, trained_imgsz)
    from omnigen.files import atomic_write_json
    from omnigen.progress import print_table

    ds = Dataset.open(a.dataset, show_progress=False)
    chosen = split_frames(str(a.dataset), None if a.split == "all" else a.split) or list(ds.table.frame_id)
    if a.frames < len(chosen):
        chosen = [chosen[i] for i in np.linspace(0, len(chosen) - 1, a.frames).round().astype(int)]
    model, state = load_for_prediction(a.weights, "cpu")
    imgsz = trained_imgsz(state)
    data = KeypointDataset(a.dataset, checkpoint_taxonomy(state), imgsz, chosen)
    # the corners as placed: the script snaps them itself, once per variant
    opts = PredictOptions(imgsz=imgsz, conf=EVAL_CONF, max_det=EVAL_MAX_DET, multi_label=EVAL_MULTI_LABEL,
                          vertical="off")
    predictions = predict_frames(model, data, opts, show_progress=True)
    frames = [str(f) for f in chosen]
    views = sorted({str(ds.table.view[ds.index_of(f)]) for f in frames})

    def gray_of(image_id: int) -> np.ndarray:
        image = cv2.imread(str(ds.path(ds[image_id - 1].image)), cv2.IMREAD_GRAYSCALE)
        if image is None:
            raise SystemExit(f"vertical_snap: {ds.path(ds[image_id - 1].image)}: unreadable image")
        return image

    off_adherence, off_map = adherence_and_map(ds, predictions, frames)
    figures: dict[str, dict] = {"off": {"adherence_deg": off_adherence, "oks_map50_95": off_map}}
    for name, snap in variants:
        out, points, seconds = snapped(predictions, gray_of, snap)
        errors: dict[str, dict[str, list[float]]] = defaultdict(lambda: {"first": [], "lines": []})
        for image_id, (first, v) in points.items():
            f = image_id - 1
            plane = ds.table.ground_plane[f]
            if not np.isfinite(plane).all():
                continue
            truth = true_point(ds.table.K[f], plane, float(ds.table.width[f]), float(ds.table.height[f]))
            for group in ("overall", str(ds.table.view[f])):
                errors[group]["first"].append(point_error_deg(first, truth))
                errors[group]["lines"].append(point_error_deg(v, truth))
        adherence, mean_ap = adherence_and_map(ds, out, frames)
        figures[name] = {"options": snap.__dict__, "adherence_deg": adherence, "oks_map50_95": mean_ap,
                         "snap_ms_median": 1000 * float(np.median(seconds)) if seconds else float("nan"),
                         "point_error_deg": {g: {k: {"median": float(np.median(x)), "mean": float(np.mean(x)),
                                                     "frames": len(x)} for k, x in e.items()}
                                             for g, e in errors.items()}}
    groups = ["overall", *views]
    rows = [("off", "-", "-", *[f"{off_adherence.get(g, float('nan')):.2f}" for g in groups], f"{off_map:.4f}")]
    for name, _ in variants:
        f = figures[name]
        e = f["point_error_deg"].get("overall", {})
        rows.append((name, *[f"{e[k]['median']:.2f} ({e[k]['mean']:.2f})" if k in e else "-" for k in ("first", "lines")],
                     *[f"{f['adherence_deg'].get(g, float('nan')):.2f}" for g in groups], f"{f['oks_map50_95']:.4f}"))
    print_table(f"vertical edges snapped: {len(frames)} frames of {a.split}; point error deg median (mean) over frames",
                ["corners", "point error, first", "point error, lines", *[f"adherence {g}" for g in groups],
                 "OKS mAP50:95"], rows)
    for name, _ in variants:
        per_view = figures[name]["point_error_deg"]
        print(f"{name}: point error by view, lines (first), median: " + "; ".join(
            f"{g} {per_view[g]['lines']['median']:.2f} ({per_view[g]['first']['median']:.2f})"
            for g in views if g in per_view) + f"; snap {figures[name]['snap_ms_median']:.1f} ms an image, median")
    if a.out:
        atomic_write_json(a.out, {"dataset": str(a.dataset), "weights": str(a.weights), "split": a.split,
                                  "frames": frames, "figures": figures}, indent=1)
    d = figures["default"]
    e = d["point_error_deg"].get("overall", {})
    print(f"vertical_snap: adherence off {off_adherence.get('overall', float('nan')):.2f} deg, snapped "
          f"{d['adherence_deg'].get('overall', float('nan')):.2f}; point error "
          f"{e.get('lines', {}).get('median', float('nan')):.2f} deg (first "
          f"{e.get('first', {}).get('median', float('nan')):.2f}), median over frames; mAP50:95 off {off_map:.4f}, "
          f"snapped {d['oks_map50_95']:.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
