"""How much metric 3D depends on the intrinsics given to the lifting.

The keypoint detector never sees K; K enters only when predicted corners are lifted to metric
boxes (detector/bev/lift.py). This command lifts the same predictions with K perturbed (focal length
x0.98, x0.95, x0.90; principal point shifted by +50 px in x, then in y), writes KITTI label
folders of the ground truth and of each lift, and reports KITTI AP (BEV, 3D) for each, beside the
keypoint metrics, which are identical by construction (the 2D predictions do not change).

What it shows and what it does not: docs/metric-3d.md. The --out JSON's first key,
"omnigen": "calib-sensitivity", lets a rerun replace it; any other file there is refused.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import numpy as np

from omnigen.detector.prediction.results_file import read_results
from omnigen.conventions import FINE_CLASSES, NUM_KEYPOINTS
from omnigen.dataset import Dataset
from omnigen.files import atomic_write_bytes
from omnigen.formats.checks import naming_frame
from omnigen.formats.kitti import kitti_file_names, label_text
from omnigen.outputs import MARK_KEY, check_output_file, json_made_by, write_output_file
from omnigen.progress import print_table
from omnigen.splits import TRAIN, read_split, split_names
from omnigen.taxonomy import Taxonomy, load_taxonomy

JOB = "calib-sensitivity"

if TYPE_CHECKING:  # the lift (and cv2 with it) is imported where it is used, not when `omnigen --help` builds the parser
    from omnigen.detector.bev.lift import DimensionPriors


@dataclass(frozen=True)
class Perturbation:
    """A change of K: focal lengths times `focal_scale`, principal point moved by the shifts (px)."""

    name: str
    focal_scale: float = 1.0
    cx_shift: float = 0.0
    cy_shift: float = 0.0

    def apply(self, K: np.ndarray) -> np.ndarray:
        out = np.array(K, dtype=np.float64).reshape(3, 3)
        out[0, 0] *= self.focal_scale
        out[1, 1] *= self.focal_scale
        out[0, 2] += self.cx_shift
        out[1, 2] += self.cy_shift
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"name": self.name, "focal_scale": self.focal_scale, "cx_shift": self.cx_shift, "cy_shift": self.cy_shift}


PERTURBATIONS: tuple[Perturbation, ...] = (
    Perturbation("reference"),
    Perturbation("focal x0.98", focal_scale=0.98),
    Perturbation("focal x0.95", focal_scale=0.95),
    Perturbation("focal x0.90", focal_scale=0.90),
    Perturbation("cx +50 px", cx_shift=50.0),
    Perturbation("cy +50 px", cy_shift=50.0),
)
"""The first is the reference every other row is compared with."""

DEFAULT_VIEWS = ("ego",)
"""KITTI's box parameterisation (rotation_y about the camera's y, upright boxes) is faithful only
for level cameras; pitched pole and drone views lose their tilt in it (docs/metric-3d.md)."""


# ---------------------------------------------------------------------------------------------
# Predictions
# ---------------------------------------------------------------------------------------------


@dataclass
class FramePredictions:
    """One frame's detections: keypoints (n, 8, 2), valid (n, 8), fine class names, scores, xyxy boxes."""

    keypoints: np.ndarray
    valid: np.ndarray
    categories: list[str]
    scores: np.ndarray
    boxes: np.ndarray


def representative_fine_classes(taxonomy: Taxonomy, priors: DimensionPriors) -> list[str]:
    """For each target class (by 0-based id), the fine class whose size prior stands for it: the
    member with the most training objects (vehicle -> car in practice), ties in FINE_CLASSES order."""
    out = []
    for target in taxonomy.classes:
        members = [c for c in FINE_CLASSES if taxonomy.target(c) == target]
        out.append(max(members, key=lambda c: (priors.counts.get(c, 0), -FINE_CLASSES.index(c))))
    return out


def keypoint_box(kp: np.ndarray, width: int, height: int) -> np.ndarray:
    """[x, y, w, h] around the used corners of (8, 3) x, y, v rows, clipped to the image."""
    xy = kp[~(kp == 0).all(axis=1), :2]
    if not len(xy):
        return np.zeros(4)
    lo = np.clip(xy.min(axis=0), -0.5, [width - 0.5, height - 0.5])
    hi = np.clip(xy.max(axis=0), -0.5, [width - 0.5, height - 0.5])
    return np.concatenate([lo, hi - lo])


def load_predictions(path: Path, ds: Dataset, fine_of_class: list[str]) -> dict[int, FramePredictions]:
    """COCO-results detections grouped by frame index.

    Each entry: image_id (1-based frame order, as omnigen.formats.coco.to_coco numbers images) or
    frame_id; category_id (1-based taxonomy class); keypoints (24 numbers: x, y, score per
    corner); bbox [x, y, w, h] (optional: else the used corners' box, clipped to the image); score.
    A corner written 0 0 0 (COCO's "not labelled") is not used.
    """
    data = read_results(path)
    grouped: dict[int, list[tuple]] = {}
    for n, d in enumerate(data):
        where = f"{path}: detection {n}"
        if not isinstance(d, dict):
            raise ValueError(f"{where}: not an object")
        if "frame_id" in d:
            try:
                frame = ds.index_of(str(d["frame_id"]))
            except KeyError:
                raise ValueError(f"{where}: field 'frame_id': no frame {d['frame_id']!r} in {ds.root}") from None
        elif isinstance(d.get("image_id"), int) and not isinstance(d["image_id"], bool) and 1 <= d["image_id"] <= len(ds):
            frame = d["image_id"] - 1
        else:
            raise ValueError(f"{where}: field 'image_id' must be an integer in 1..{len(ds)} (or give 'frame_id')")
        cid = d.get("category_id")
        if not isinstance(cid, int) or not 1 <= cid <= len(fine_of_class):
            raise ValueError(f"{where}: field 'category_id' must be an integer in 1..{len(fine_of_class)}")
        kp = np.asarray(d.get("keypoints", []), dtype=np.float64)
        if kp.shape != (3 * NUM_KEYPOINTS,) or not np.isfinite(kp).all():
            raise ValueError(f"{where}: field 'keypoints' must be {3 * NUM_KEYPOINTS} finite numbers")
        if d.get("bbox") is None:  # keypoint-only results: the corners' box, clipped to the image
            bbox = keypoint_box(kp.reshape(NUM_KEYPOINTS, 3), int(ds.table.width[frame]), int(ds.table.height[frame]))
        else:
            bbox = np.asarray(d["bbox"], dtype=np.float64)
            if bbox.shape != (4,) or not np.isfinite(bbox).all():
                raise ValueError(f"{where}: field 'bbox' must be 4 finite numbers [x, y, w, h]")
        score = d.get("score")
        if not isinstance(score, (int, float)):
            raise ValueError(f"{where}: field 'score' must be a number")
        grouped.setdefault(frame, []).append((kp.reshape(NUM_KEYPOINTS, 3), fine_of_class[cid - 1], float(score), bbox))
    out = {}
    for frame, dets in grouped.items():
        kp = np.array([k for k, *_ in dets])
        boxes = np.array([b for *_, b in dets])
        out[frame] = FramePredictions(
            keypoints=kp[..., :2], valid=~(kp == 0).all(axis=2), categories=[c for _, c, _, _ in dets],
            scores=np.array([s for _, _, s, _ in dets]), boxes=np.concatenate([boxes[:, :2], boxes[:, :2] + boxes[:, 2:]], 1))
    return out


# ---------------------------------------------------------------------------------------------
# Lifting under each perturbation
# ---------------------------------------------------------------------------------------------


@dataclass
class LiftSummary:
    """Per perturbation, what the lift did before any AP is computed."""

    lines: dict[int, list[str]]  # frame index -> KITTI result lines
    depth: np.ndarray  # (all detections,) lifted depth z, NaN where the lift failed
    adherence: np.ndarray  # (all detections,) degrees to the frame's true ground plane, NaN if unknown


def lift_frames(ds: Dataset, frames: list[int], preds: dict[int, FramePredictions], priors: DimensionPriors,
                perturbation: Perturbation) -> LiftSummary:
    """Lift every frame's predictions with K perturbed; detections in frame order."""
    from omnigen.detector.bev.lift import ground_adherence_deg, lift_keypoints, to_kitti_lines

    lines, depth, adherence = {}, [], []
    for f in frames:
        p = preds.get(f)
        if p is None or not len(p.scores):
            lines[f] = []
            continue
        K = perturbation.apply(ds.table.K[f])
        lifted = lift_keypoints(p.keypoints, priors.dims_for(p.categories), K, valid=p.valid)
        lines[f] = to_kitti_lines(lifted, p.categories, p.boxes, scores=p.scores)
        depth.append(lifted.t[:, 2])
        plane = ds.table.ground_plane[f]
        adherence.append(ground_adherence_deg(lifted, plane) if np.isfinite(plane).all() else np.full(len(lifted), np.nan))
    cat = lambda xs: np.concatenate(xs) if xs else np.zeros(0)  # noqa: E731
    return LiftSummary(lines, cat(depth), cat(adherence))


def write_label_folder(folder: Path, names: dict[int, str], lines: dict[int, list[str]]) -> None:
    """One <number>.txt per frame (empty when the frame has no detection), as KITTI expects."""
    for f, number in names.items():
        text = "".join(f"{line}\n" for line in lines.get(f, []))
        atomic_write_bytes(folder / f"{number}.txt", text.encode(), durable=False)


def write_ground_truth(ds: Dataset, folder: Path, names: dict[int, str]) -> None:
    """Ground-truth labels exactly as `omnigen export kitti` writes them (DontCare included)."""
    for f, number in names.items():
        with naming_frame(ds, f):
            text = label_text(ds[f])
        atomic_write_bytes(folder / f"{number}.txt", text.encode(), durable=False)


def _median(x: np.ndarray) -> float | None:
    x = x[np.isfinite(x)]
    return float(np.median(x)) if len(x) else None


def _mean(x: np.ndarray) -> float | None:
    x = x[np.isfinite(x)]
    return float(np.mean(x)) if len(x) else None


def sensitivity(ds: Dataset, frames: list[int], preds: dict[int, FramePredictions], priors: DimensionPriors,
                evaluate: Callable[[str, str], dict] | None, workdir: Path,
                perturbations: tuple[Perturbation, ...] = PERTURBATIONS) -> list[dict[str, Any]]:
    """One result per perturbation: lift counts, depth ratio to the reference lift, ground
    adherence, and (when `evaluate` is given) the KITTI AP dict of evaluate_folders."""
    ids = [ds.frame_ids[f] for f in frames]
    by_id = kitti_file_names(ids)
    names = {f: by_id[ds.frame_ids[f]] for f in frames}
    gt_dir = workdir / "gt"
    write_ground_truth(ds, gt_dir, names)
    results, reference = [], None
    for k, pert in enumerate(perturbations):
        summary = lift_frames(ds, frames, preds, priors, pert)
        if reference is None:
            reference = summary.depth
        pred_dir = workdir / f"pred_{k}"
        write_label_folder(pred_dir, names, summary.lines)
        ok = np.isfinite(summary.depth)
        both = ok & np.isfinite(reference)
        results.append({
            **pert.to_dict(),
            "detections": int(len(summary.depth)), "lifted": int(ok.sum()),
            "median_depth_ratio": _median(summary.depth[both] / reference[both]) if both.any() else None,
            "mean_ground_adherence_deg": _mean(summary.adherence),
            "kitti": evaluate(str(gt_dir), str(pred_dir)) if evaluate is not None else None,
        })
    return results


# ---------------------------------------------------------------------------------------------
# The command
# ---------------------------------------------------------------------------------------------


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("predictions", type=Path, help="detections in COCO results form (JSON list)")
    p.add_argument("dataset", type=Path)
    p.add_argument("--split", default="test", help="frames to evaluate (splits/<name>.txt); 'all' for every frame")
    p.add_argument("--views", default=",".join(DEFAULT_VIEWS),
                   help="comma-separated views to evaluate (default ego: KITTI's boxes assume a level camera)")
    p.add_argument("--sources", default="all", help="comma-separated sources to evaluate (default all)")
    p.add_argument("--taxonomy", default="fine", help="taxonomy the predictions' category ids index (default fine)")
    p.add_argument("--priors", type=Path, default=None,
                   help="dimension priors JSON (DimensionPriors.to_dict); default: fitted on the train split")
    p.add_argument("--out", type=Path, default=None,
                   help="write the results here as JSON (a new file, or one calib-sensitivity wrote)")


def select_frames(ds: Dataset, split: str, views: str, sources: str) -> list[int]:
    keep = None if split == "all" else set(read_split(ds.root, split))
    want_views = None if views == "all" else set(views.split(","))
    want_sources = None if sources == "all" else set(sources.split(","))
    t = ds.table
    return [i for i, f in enumerate(t.frame_id)
            if (keep is None or f in keep) and (want_views is None or t.view[i] in want_views)
            and (want_sources is None or t.source[i] in want_sources)]


def load_priors(ds: Dataset, path: Path | None) -> tuple[DimensionPriors, str]:
    """Priors from a file, else the train split's medians, else (no train split) the fixed priors
    of omnigen/priors.py: never the evaluated frames' own sizes."""
    from omnigen.detector.bev.lift import DimensionPriors, fit_dimension_priors

    if path is not None:
        try:
            return DimensionPriors.from_dict(json.loads(Path(path).read_bytes()), str(path)), str(path)
        except (OSError, json.JSONDecodeError) as exc:
            raise ValueError(f"{path}: cannot read priors: {exc}") from None
    if TRAIN in split_names(ds.root):
        return fit_dimension_priors(ds, read_split(ds.root, TRAIN)), "train split medians"
    return fit_dimension_priors(ds, []), "fixed class priors (no train split)"


def _fmt_percent(v: float | None) -> str:
    return "-" if v is None or not np.isfinite(v) else f"{100 * v:.2f}"


def _ap(result: dict, metric: str, cls: str = "Car") -> float | None:
    """Moderate AP (R40) for a class and metric, or None where the evaluator gave none."""
    try:
        return float(result["kitti"]["AP40"][cls][metric][1])
    except (KeyError, TypeError, IndexError):
        return None


def keypoint_metrics_of(args: argparse.Namespace, ds: Dataset, taxonomy: Taxonomy) -> dict[str, Any] | None:
    """OKS mAP50:95 and AP at OKS 0.5 of the same predictions (detector/evaluation/oks_eval.py), for the
    evaluated view when one is selected, else over the split; None where oks_eval is absent."""
    try:
        from omnigen.detector.evaluation.oks_eval import evaluate as oks_evaluate
    except ImportError:
        return None
    predictions = read_results(args.predictions)
    report = oks_evaluate(ds, predictions, None if args.split == "all" else args.split, taxonomy,
                          adherence=False, source=str(args.predictions))
    views = args.views.split(",")
    group = f"view={views[0]}" if len(views) == 1 and views[0] != "all" else "overall"
    try:
        row = report.row(group)
    except KeyError:
        return None
    undefined = lambda v: None if v is None or not np.isfinite(v) else float(v)  # noqa: E731  (JSON has no NaN)
    return {"group": group, "oks_map50_95": undefined(row.oks_map50_95), "ap_oks50": undefined(row.ap_oks50)}


def run(args: argparse.Namespace) -> int:
    inputs = [args.predictions, args.dataset] + ([args.priors] if args.priors is not None else [])
    if args.out is not None:  # before the lifts: a refused --out costs nothing
        check_output_file(args.out, JOB, json_made_by(JOB), inputs)
    ds = Dataset.open(args.dataset)
    priors, priors_from = load_priors(ds, args.priors)
    taxonomy = load_taxonomy(args.taxonomy)
    preds = load_predictions(args.predictions, ds, representative_fine_classes(taxonomy, priors))
    frames = select_frames(ds, args.split, args.views, args.sources)
    if not frames:
        raise SystemExit(f"{args.dataset}: no frame of split {args.split!r} with views {args.views} and sources "
                         f"{args.sources} (try --views all)")
    try:
        from omnigen.detector.evaluation.kitti_eval import evaluate_folders
    except ImportError as exc:
        print(f"KITTI AP unavailable ({exc}); reporting the lift only")
        evaluate_folders = None
    keypoint_metrics = keypoint_metrics_of(args, ds, taxonomy)
    with tempfile.TemporaryDirectory(prefix="calib-sensitivity-") as tmp:
        results = sensitivity(ds, frames, preds, priors, evaluate_folders, Path(tmp))
    oks = "-" if keypoint_metrics is None else _fmt_percent(keypoint_metrics["oks_map50_95"])
    rows = []
    for r in results:
        rows.append([r["name"], f"{r['lifted']}/{r['detections']}",
                     "-" if r["median_depth_ratio"] is None else round(r["median_depth_ratio"], 4),
                     "-" if r["mean_ground_adherence_deg"] is None else round(r["mean_ground_adherence_deg"], 2),
                     *("-" if _ap(r, m, c) is None else round(_ap(r, m, c), 2)
                       for c, m in (("Car", "bev"), ("Car", "3d"), ("Pedestrian", "3d"), ("Cyclist", "3d"))),
                     oks])
    print_table(f"calibration sensitivity: {len(frames)} frames, priors: {priors_from}; AP: KITTI R40 moderate, %",
                ["K", "lifted", "z/ref", "adh deg", "Car BEV", "Car 3D", "Ped 3D", "Cyc 3D", "OKS mAP"], rows)
    print("z/ref: median lifted depth over the reference lift's; adh deg: mean angle of the lifted bottom edges "
          "to the true ground plane.\nKeypoint metrics (OKS mAP50:95 and the rest) are identical in every row: "
          "the 2D predictions do not change, only the K they are lifted with.")
    if args.out is not None:
        write_output_file(args.out, (json.dumps({
            MARK_KEY: JOB, "dataset": str(args.dataset), "predictions": str(args.predictions), "split": args.split,
            "views": args.views, "sources": args.sources, "frames": len(frames), "priors_from": priors_from,
            "priors": priors.to_dict(), "perturbations": results,
            "keypoint_metrics": keypoint_metrics,
            "keypoint_metrics_note": "identical in every row by construction: the same 2D predictions",
        }, indent=2, allow_nan=False) + "\n").encode(), JOB, json_made_by(JOB), inputs)
    return 0
