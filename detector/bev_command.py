"""The calibration-free BEV of every image in a predictions file.

PREDICTIONS is COCO-results JSON: a list of {image_id, category_id, keypoints (24 numbers: x, y, v
per corner, contract order), bbox [x, y, w, h], score}. Detections whose ground-contact corners 4-7
all have v > 0 define the image's homography (omnigen.detector.bev.homography.rectify); the others, and entries with
no keypoints at all (an auxiliary 2D detector's), are placed in the BEV by the ridge map fitted on
the image's keypoint detections. Per image it writes DIR/<image_id>.json and DIR/<image_id>.png.

DIR is claimed for bev (.omnigen-job, omnigen.ownership): a folder holding anything else is
refused, as is one that is, lies inside or holds the predictions file or the --images folder. An
image that cannot be read (over omnigen.images' caps, undecodable) is listed on stderr and its BEV
drawn on a grey canvas; a figure over omnigen.draw.MAX_CANVAS_PIXELS (an image of an extreme aspect
ratio) is listed and not drawn; either way the run exits 1. Without an image, the grey canvas
reaches the detections' extent up to PLACEHOLDER_MAX_SIDE a side.

category_id is 1-based into the taxonomy's classes (as omnigen's COCO export writes it); the
class names choose the aspect and size priors.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from omnigen.detector.prediction.results_file import read_results
from omnigen.detector.bev.homography import RIDGE_LAMBDA, apply_homography, fit_ridge, rectify
from omnigen.conventions import BOTTOM_CORNERS, NUM_KEYPOINTS
from omnigen.options import fraction, number

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".webp")


@dataclass
class Detection:
    index: int  # position in the predictions file
    image_id: int | str
    category_id: int
    score: float
    bbox: np.ndarray | None  # (4,) xywh
    keypoints: np.ndarray | None  # (8, 3)
    file_name: str | None = None  # the image's file name, as `omnigen predict` writes it beside each detection

    @property
    def has_ground(self) -> bool:
        return self.keypoints is not None and bool((self.keypoints[list(BOTTOM_CORNERS), 2] > 0).all())

    def box_xywh(self) -> np.ndarray:
        """The 2D box; for a keypoint detection without one, the box around its visible corners."""
        if self.bbox is not None:
            return self.bbox
        kp = self.keypoints[self.keypoints[:, 2] > 0, :2]
        lo, hi = kp.min(0), kp.max(0)
        return np.array([*lo, *(hi - lo)])


PLACEHOLDER_MAX_SIDE = 4096
"""Largest side of the grey canvas drawn where an image has no picture (no --images, or none of its
name): the canvas reaches the detections' extent, a 4K frame's width at most; what lies further out
is clipped. The predictions file is what sizes it, and 153 bytes can name a corner at 40000 px."""

MAX_RIDGE_LAMBDA = 1e6
"""Largest --ridge-lambda: far past where the ridge map places every 2D-only box at the mean centre."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("predictions", type=Path, help="COCO-results JSON (image_id, category_id, keypoints, bbox, score)")
    parser.add_argument("--out", type=Path, required=True,
                        help="new or empty folder (or one of an earlier bev) for <image_id>.json and <image_id>.png")
    parser.add_argument("--images", type=Path, default=None,
                        help="folder of the pictures to draw under: the files the predictions name (file_name, as "
                             "omnigen predict writes it), else <image_id>.png/.jpg")
    parser.add_argument("--score-thr", type=fraction(), default=0.25,
                        help="drop detections scoring below, in [0, 1] (default 0.25)")
    parser.add_argument("--taxonomy", default="fine", help="taxonomy whose classes category_id counts (default fine)")
    parser.add_argument("--ridge-lambda", type=number(0.0, MAX_RIDGE_LAMBDA), default=RIDGE_LAMBDA,
                        help="ridge strength for 2D-only boxes")
    parser.add_argument("--no-draw", action="store_true", help="write the JSON only")


def _number_list(path: Path, i: int, entry: dict, key: str, length: int) -> np.ndarray:
    value = entry[key]
    if not isinstance(value, list) or len(value) != length or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value):
        raise ValueError(f"{path}: entry {i}: field '{key}': expected {length} finite numbers, got {str(value)[:80]}")
    return np.asarray(value, dtype=np.float64)


def load_predictions(path: Path, n_classes: int) -> list[Detection]:
    """Parse and check a COCO-results file; errors name the file, the entry and the field."""
    data = read_results(path)
    out = []
    for i, entry in enumerate(data):
        if not isinstance(entry, dict):
            raise ValueError(f"{path}: entry {i}: expected an object, got {type(entry).__name__}")
        for key in ("image_id", "category_id"):
            if key not in entry:
                raise ValueError(f"{path}: entry {i}: field '{key}' is missing")
        image_id = entry["image_id"]
        if isinstance(image_id, bool) or not isinstance(image_id, (int, str)) or (
                isinstance(image_id, str) and (not image_id or "/" in image_id or image_id.startswith("."))):
            raise ValueError(f"{path}: entry {i}: field 'image_id': expected an integer or a plain name, got {image_id!r}")
        cid = entry["category_id"]
        if isinstance(cid, bool) or not isinstance(cid, int) or not 1 <= cid <= n_classes:
            raise ValueError(f"{path}: entry {i}: field 'category_id': expected an integer in 1..{n_classes}, got {cid!r}")
        score = entry.get("score", 1.0)
        if isinstance(score, bool) or not isinstance(score, (int, float)) or not math.isfinite(score):
            raise ValueError(f"{path}: entry {i}: field 'score': expected a number, got {score!r}")
        kp = _number_list(path, i, entry, "keypoints", 3 * NUM_KEYPOINTS).reshape(NUM_KEYPOINTS, 3) \
            if entry.get("keypoints") is not None else None
        bbox = _number_list(path, i, entry, "bbox", 4) if entry.get("bbox") is not None else None
        if bbox is not None and (bbox[2] <= 0 or bbox[3] <= 0):
            raise ValueError(f"{path}: entry {i}: field 'bbox': width and height must be positive, got {bbox.tolist()}")
        if bbox is None and (kp is None or not (kp[:, 2] > 0).any()):
            raise ValueError(f"{path}: entry {i}: field 'bbox' is missing and there are no keypoints to place it by")
        file_name = entry.get("file_name")
        if file_name is not None and (not isinstance(file_name, str) or not Path(file_name).name):
            raise ValueError(f"{path}: entry {i}: field 'file_name': expected a file name, got {str(file_name)[:80]!r}")
        out.append(Detection(i, image_id, cid, float(score), bbox, kp, file_name))
    return out


def find_image(folder: Path | None, image_id: int | str, file_name: str | None = None) -> Path | None:
    """The picture of one image in `folder` (--images): by the name of the file the predictions
    were made from (`omnigen predict` writes it beside each detection; its ids are numbers), else
    named by its image id. Only `folder` is searched, by a base name: a path in a predictions file
    is never opened as it stands (a file names nothing outside the inputs it was given)."""
    if folder is None:
        return None
    names = ([Path(file_name).name] if file_name else []) + [f"{image_id}{suffix}" for suffix in IMAGE_SUFFIXES]
    for name in names:
        p = folder / name
        if p.is_file():
            return p
    return None


def bev_for_image(dets: list[Detection], classes: list[str], lam: float) -> dict[str, Any]:
    """The head on one image's detections: the result, the placed 2D-only boxes, and the JSON record."""
    kp = [d for d in dets if d.has_ground]
    flat = [d for d in dets if not d.has_ground]
    names = [classes[d.category_id - 1] for d in kp]
    record: dict[str, Any] = {"image_id": dets[0].image_id, "homography": None, "detections": [], "placed_2d": [],
                              "ridge": {"lambda": lam, "features": ["cx", "cy", "w", "h", "w/h"], "bias": True}}
    result, placed = None, np.zeros((0, 2))
    ground = np.stack([d.keypoints[list(BOTTOM_CORNERS), :2] for d in kp]) if kp else np.zeros((0, 4, 2))
    if kp:
        try:
            result = rectify(ground, names)
        except (ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:  # one bad image, not the run
            record["error"] = f"not rectified: {exc.__class__.__name__}: {exc}"
    if result is not None:
        record.update(homography=result.homography.tolist(), degenerate=result.degenerate, residual=result.residual,
                      iterations=result.iterations, folded=result.folded)
        for j, d in enumerate(kp):
            record["detections"].append({
                "index": d.index, "category_id": d.category_id, "class": names[j], "score": d.score,
                "footprint": result.footprints[j].tolist(), "centre": result.centres[j].tolist(),
                "heading": float(result.headings[j]), "angle_error_deg": float(result.angle_error_deg[j])})
        if flat:
            ridge = fit_ridge(np.stack([d.box_xywh() for d in kp]), result.centres, lam)
            placed = ridge(np.stack([d.box_xywh() for d in flat]))
    for j, d in enumerate(flat):
        box = d.box_xywh()
        via_h = None
        if result is not None:  # the box's bottom-centre, where it meets the ground, through H
            via_h = apply_homography(result.homography, np.array([box[0] + box[2] / 2, box[1] + box[3]])).tolist()
        record["placed_2d"].append({"index": d.index, "category_id": d.category_id, "score": d.score,
                                    "bbox": box.tolist(), "centre": placed[j].tolist() if len(placed) else None,
                                    "centre_bottom_through_h": via_h})
    return {"record": record, "result": result, "ground": ground, "names": names,
            "boxes_2d": np.stack([d.box_xywh() for d in flat]) if flat else np.zeros((0, 4)), "placed": placed}


def placeholder_size(points: np.ndarray) -> tuple[int, int]:
    """(width, height) of the grey canvas under detections with no image: up to the farthest point
    plus a border, at least 1 and at most PLACEHOLDER_MAX_SIDE pixels a side."""
    far = points.max(0) + 20
    return tuple(int(min(max(v, 1), PLACEHOLDER_MAX_SIDE)) for v in far)


def draw_image(out: dict[str, Any], image_id: int | str, images: Path | None,
               file_name: str | None = None) -> tuple[Any, str | None]:
    """One image's BEV figure (a PIL image), and why its picture is not under it (None when it is,
    or when there is none to draw). Raises ValueError when the figure would be too large to draw."""
    from omnigen.detector.bev.draw import BevScene, render_bev_figure
    from omnigen.images import ImageError, read_rgb

    path = find_image(images, image_id, file_name)
    image, problem = None, None
    if path is None and images is not None:
        wanted = Path(file_name).name if file_name else f"{image_id}.png"
        problem = f"image {image_id}: no {wanted} in {images}; the BEV is drawn on a grey canvas"
    if path is not None:
        try:
            image = read_rgb(path)  # size-capped before decoding (omnigen.images)
        except (ImageError, OSError) as exc:
            problem = f"{exc}; the BEV is drawn on a grey canvas"
    boxes = out["boxes_2d"]
    pts = np.concatenate([out["ground"].reshape(-1, 2), boxes[:, :2].reshape(-1, 2), boxes[:, :2] + boxes[:, 2:]])
    w, h = image.size if image else placeholder_size(pts)
    title = f"{image_id}: {len(out['names'])} footprints, {len(out['placed'])} 2D-only" + (
        "" if image else "  [no image]")
    scene = BevScene(out["ground"], out["names"], out["result"], boxes, out["placed"], title)
    return render_bev_figure(scene, image, w, h, what=f"image {image_id}"), problem


def run(args: argparse.Namespace) -> int:
    from omnigen.detector.predict_command import claim_folder
    from omnigen.files import atomic_write_json
    from omnigen.outputs import refuse_inputs, save_image
    from omnigen.progress import print_table, progress
    from omnigen.taxonomy import load_taxonomy

    classes = load_taxonomy(args.taxonomy).classes
    dets = [d for d in load_predictions(args.predictions, len(classes)) if d.score >= args.score_thr]
    refuse_inputs(args.out, [args.predictions] + ([args.images] if args.images else []), "bev")
    claim_folder(args.out, "bev")
    by_image: dict[int | str, list[Detection]] = {}
    for d in dets:
        by_image.setdefault(d.image_id, []).append(d)
    rows, t0 = [], time.perf_counter()
    for image_id, group in progress(sorted(by_image.items(), key=lambda kv: str(kv[0])), "bev", unit="img"):
        out, problem = bev_for_image(group, classes, args.ridge_lambda), None
        atomic_write_json(args.out / f"{image_id}.json", out["record"])
        res = out["result"]
        if not args.no_draw:
            try:
                figure, problem = draw_image(out, image_id, args.images, group[0].file_name)
                save_image(figure, args.out / f"{image_id}.png", "bev")
            except ValueError as exc:  # too large a figure: the JSON stands, the picture is not drawn
                problem = f"{exc}; not drawn"
            if problem is not None:
                print(f"skipped: {problem}", file=sys.stderr)
        rows.append((str(image_id), len(out["names"]), len(out["placed"]),
                     "-" if res is None else float(np.median(res.angle_error_deg)),
                     "-" if res is None else ("yes" if res.degenerate else "no"), int(problem is not None)))
    elapsed = time.perf_counter() - t0
    shown = rows if len(rows) <= 20 else rows[:20]
    footprints, skipped = sum(r[1] for r in rows), sum(r[5] for r in rows)
    print_table(f"omnigen bev: {len(rows)} images -> {args.out} ({elapsed:.1f} s)",
                ["image", "footprints", "2D-only placed", "median angle err (deg)", "one heading", "skipped"],
                shown + ([("...", "", "", "", "", "")] if len(rows) > 20 else []) +
                [("all", footprints, sum(r[2] for r in rows),
                  "", f"{sum(r[4] == 'yes' for r in rows)} of {len(rows)}", skipped)])
    if args.images is None and not args.no_draw:
        print("no --images: the BEVs are drawn on grey; pass the folder the predictions were made from to draw them "
              "under their pictures")
    return 1 if skipped else 0
