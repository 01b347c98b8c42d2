"""KITTI object-detection AP (2D box, bird's-eye view, 3D; R40 and R11) on the CPU.

The numbers are the official devkit's (cpp/evaluate_object.cpp of the KITTI object devkit), rule for
rule, because published KITTI figures are only comparable when every quirk is the same:

- Classes Car (overlap 0.7), Pedestrian and Cyclist (0.5), for all three box kinds. An overlap
  counts only when it is strictly greater than the threshold (`overlap > min_overlap`).
- Difficulties Easy, Moderate, Hard: a ground-truth object counts when its 2D box is at least
  40/25/25 px tall (`height < MIN_HEIGHT` ignores it: the C++ rule; the popular Python port
  kitti-object-eval-python writes `<=`, which drops objects exactly 40.0 or 25.0 px tall), its
  occlusion is at most 0/1/2 and its truncation at most 0.15/0.30/0.50. Objects outside the
  difficulty are ignored: neither TP nor FN, but a detection matched to them is not a FP.
- Neighbouring classes (Van for Car, Person_sitting for Pedestrian) are ignored the same way.
- Any detection lower than the difficulty's minimum height, of any class, is an "ignored
  detection": it may be matched (so the object it covers is not a FN) and is never a FP.
- DontCare regions: an unmatched detection covering a DontCare region by more than the class
  overlap (intersection over the detection's own area) is not a FP. The devkit applies the same
  overlap function as the metric; DontCare labels carry -1000 placeholders as their 3D box, so in
  BEV and 3D no detection ever overlaps one: the rule acts on the 2D box only (as in the Python port).
- Matching, per frame, ground truth in file order: to collect score thresholds, each object takes the
  highest-scored unmatched detection above the overlap; for the precision/recall points, the one
  with the greatest overlap (an ignored detection only when no valid one overlaps).
- The 41 score thresholds are sampled from the scores of the true positives with the number of valid
  ground-truth objects as the recall denominator (`get_thresholds`). Precision at threshold i is
  stored at recall position i, so a class with fewer than 41 valid objects gets fewer than 41
  points and its AP is capped: n objects, all found, give AP40 = (n - 1) / 40 and AP11 =
  ceil(n / 4) / 11 (n <= 40). This is the official definition, not a bug to fix here.
- Precision is made monotone (max to the right); AP11 averages points 0, 4, ..., 40, AP40 points
  1..40; results are in percent. A class without valid objects scores 0.

Rotated overlaps use shapely 2's vectorized GEOS intersection (exact for identical boxes, unlike the
CUDA kernel of the Python port), after a bounding-circle test that leaves only pairs that can touch.
The matching itself is vectorized across frames: only ground truth and detections that overlap
something enter the (frames x objects x detections) arrays; everything else is counted directly.
One deliberate departure: where the devkit divides 0 by 0 (no TP and no FP at a threshold, possible
only when every detection above it went to ignored objects) the precision is 0, not NaN.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np
import shapely

CLASSES: tuple[str, ...] = ("Car", "Pedestrian", "Cyclist")
METRICS: tuple[str, ...] = ("bbox", "bev", "3d")
DIFFICULTIES: tuple[str, ...] = ("easy", "moderate", "hard")
MIN_OVERLAP: dict[str, float] = {"Car": 0.7, "Pedestrian": 0.5, "Cyclist": 0.5}
NEIGHBOUR: dict[str, str] = {"car": "van", "pedestrian": "person_sitting"}
MIN_HEIGHT: tuple[float, ...] = (40.0, 25.0, 25.0)
MAX_OCCLUSION: tuple[int, ...] = (0, 1, 2)
MAX_TRUNCATION: tuple[float, ...] = (0.15, 0.30, 0.50)
N_SAMPLE_PTS = 41
NO_DETECTION = -10000000.0  # the devkit's "no candidate yet" score: detections scored below never match

GT_FIELDS: tuple[str, ...] = ("type", "truncated", "occluded", "alpha", "bbox_left", "bbox_top", "bbox_right",
                              "bbox_bottom", "height", "width", "length", "x", "y", "z", "rotation_y")
PRED_FIELDS: tuple[str, ...] = GT_FIELDS + ("score",)


class KittiFormatError(ValueError):
    """A label file that is not KITTI format; the message names the file, the line and the field."""


@dataclass(frozen=True)
class KittiLabels:
    """The objects of one frame, one row per label line, as numpy arrays (columnar: fast to evaluate)."""

    names: np.ndarray  # (N,) str, as written in the file
    truncated: np.ndarray  # (N,) float
    occluded: np.ndarray  # (N,) int
    alpha: np.ndarray  # (N,) float
    bbox: np.ndarray  # (N, 4) left, top, right, bottom in pixels
    dims: np.ndarray  # (N, 3) height, width, length in metres (KITTI's order)
    location: np.ndarray  # (N, 3) x, y, z of the bottom centre, camera frame (y down)
    rotation_y: np.ndarray  # (N,) radians about the camera y axis
    score: np.ndarray  # (N,) detection confidence; ones for ground truth

    def __len__(self) -> int:
        return len(self.names)

    @staticmethod
    def empty() -> "KittiLabels":
        return labels_from_rows([], [])


def labels_from_rows(names: Sequence[str], rows: Sequence[Sequence[float]]) -> KittiLabels:
    """Build labels from per-object numbers in file order (14 after the type, or 15 with the score)."""
    v = np.asarray(rows, dtype=np.float64).reshape(len(names), -1) if len(names) else np.zeros((0, 15))
    score = v[:, 14] if v.shape[1] > 14 else np.ones(len(names))
    return KittiLabels(names=np.asarray(names, dtype=str).reshape(-1), truncated=v[:, 0].copy(),
                       occluded=v[:, 1].astype(np.int64), alpha=v[:, 2].copy(), bbox=v[:, 3:7].copy(),
                       dims=v[:, 7:10].copy(), location=v[:, 10:13].copy(), rotation_y=v[:, 13].copy(),
                       score=np.asarray(score, dtype=np.float64).copy())


# ---------------------------------------------------------------------------------------------
# reading label folders
# ---------------------------------------------------------------------------------------------


def parse_labels(text: str, file: str, with_score: bool) -> KittiLabels:
    """Parse one KITTI label file: 15 fields a line for ground truth, 16 (with score) for predictions."""
    fields = PRED_FIELDS if with_score else GT_FIELDS
    names: list[str] = []
    rows: list[list[float]] = []
    for n, line in enumerate(text.splitlines(), start=1):
        tokens = line.split()
        if not tokens:
            continue
        if len(tokens) != len(fields):
            kind = "prediction" if with_score else "ground-truth"
            raise KittiFormatError(f"{file}:{n}: a {kind} line has {len(fields)} fields ({' '.join(fields)}), "
                                   f"found {len(tokens)}")
        values = []
        for k, token in enumerate(tokens[1:], start=1):
            try:
                x = float(token)
            except ValueError:
                raise KittiFormatError(f"{file}:{n}: field {fields[k]!r} is not a number: {token!r}") from None
            if not math.isfinite(x):
                raise KittiFormatError(f"{file}:{n}: field {fields[k]!r} is not finite: {token!r}")
            values.append(x)
        names.append(tokens[0])
        rows.append(values)
    return labels_from_rows(names, rows)


def read_labels(path: str | os.PathLike, with_score: bool) -> KittiLabels:
    path = Path(path)
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise KittiFormatError(f"{path}: not UTF-8 text ({exc.reason} at byte {exc.start})") from None
    return parse_labels(text, str(path), with_score)


def read_ids(path: str | os.PathLike) -> list[str]:
    """Frame ids from a split file (one a line, as KITTI's val.txt), blank lines skipped."""
    return [s for s in (line.strip() for line in Path(path).read_text().splitlines()) if s]


def read_folders(gt_dir: str | os.PathLike, pred_dir: str | os.PathLike,
                 ids: Iterable[str] | None = None) -> tuple[list[str], list[KittiLabels], list[KittiLabels]]:
    """Ground truth and predictions of the frames `ids` (default: every .txt in gt_dir, sorted).

    A frame without a prediction file has no detections (the devkit's submissions may omit empty
    frames); a frame without a ground-truth file is an error, since it cannot be scored.
    """
    gt_dir, pred_dir = Path(gt_dir), Path(pred_dir)
    for what, folder in (("ground-truth", gt_dir), ("prediction", pred_dir)):
        if not folder.is_dir():
            raise FileNotFoundError(f"{what} folder not found: {folder}")
    if ids is None:
        ids = sorted(p.stem for p in gt_dir.glob("*.txt") if not p.name.startswith("."))
    ids = list(ids)
    gts, preds = [], []
    for kid in ids:
        gt_file = gt_dir / f"{kid}.txt"
        if not gt_file.is_file():
            raise FileNotFoundError(f"ground truth for frame {kid!r} not found: {gt_file}")
        gts.append(read_labels(gt_file, with_score=False))
        pred_file = pred_dir / f"{kid}.txt"
        preds.append(read_labels(pred_file, with_score=True) if pred_file.is_file() else KittiLabels.empty())
    return ids, gts, preds


def evaluate_folders(gt_dir: str | os.PathLike, pred_dir: str | os.PathLike, ids: Iterable[str] | None = None,
                     classes: Sequence[str] = CLASSES) -> dict:
    """`evaluate` on KITTI label folders (gt_dir/<id>.txt, pred_dir/<id>.txt)."""
    _, gts, preds = read_folders(gt_dir, pred_dir, ids)
    return evaluate(gts, preds, classes)


# ---------------------------------------------------------------------------------------------
# overlaps
# ---------------------------------------------------------------------------------------------


def box2d_iou(a: np.ndarray, b: np.ndarray, criterion: int = -1) -> np.ndarray:
    """Row-wise overlap of 2D boxes (x1, y1, x2, y2), no +1 pixel as in the devkit.

    criterion -1: intersection over union; 0: intersection over the area of `a` (DontCare test).
    """
    w = np.minimum(a[:, 2], b[:, 2]) - np.maximum(a[:, 0], b[:, 0])
    h = np.minimum(a[:, 3], b[:, 3]) - np.maximum(a[:, 1], b[:, 1])
    touch = (w > 0) & (h > 0)
    inter = np.where(touch, w * h, 0.0)
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    if criterion == 0:
        denom = area_a
    else:
        denom = area_a + (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1]) - inter
    out = np.zeros(len(a))
    np.divide(inter, denom, out=out, where=touch & (denom > 0))
    return out


def bev_corners(location: np.ndarray, dims: np.ndarray, rotation_y: np.ndarray) -> np.ndarray:
    """(N, 4, 2) footprint corners in the camera x-z plane, as the devkit's toPolygon builds them.

    KITTI's rotation_y turns the length axis (x at 0) towards -z: corner = R (±l/2, ±w/2) + (x, z)
    with R = [[cos, sin], [-sin, cos]]. The sign matters: with the opposite one, boxes that do not
    sit at the same place would overlap differently.
    """
    c, s = np.cos(rotation_y), np.sin(rotation_y)
    l, w = dims[:, 2] / 2, dims[:, 1] / 2
    u = np.stack([l, l, -l, -l], axis=1)
    v = np.stack([w, -w, -w, w], axis=1)
    x = c[:, None] * u + s[:, None] * v + location[:, 0:1]
    z = -s[:, None] * u + c[:, None] * v + location[:, 2:3]
    return np.stack([x, z], axis=2)


def bev_intersection(corners_a: np.ndarray, corners_b: np.ndarray) -> np.ndarray:
    """Row-wise area of intersection of two arrays of convex quadrilaterals (N, 4, 2) (GEOS)."""
    if len(corners_a) == 0:
        return np.zeros(0)
    pa = shapely.polygons(corners_a)
    pb = shapely.polygons(corners_b)
    return shapely.area(shapely.intersection(pa, pb))


def rotated_overlaps(det: KittiLabels, gt: KittiLabels, d: np.ndarray, g: np.ndarray, volume: bool) -> np.ndarray:
    """BEV (volume=False) or 3D IoU of detection rows d against ground-truth rows g, pair by pair."""
    bev, box3d = bev_and_3d_overlaps(det, gt, d, g)
    return box3d if volume else bev


def bev_and_3d_overlaps(det: KittiLabels, gt: KittiLabels, d: np.ndarray, g: np.ndarray,
                        floor: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """BEV and 3D IoU of detection rows d against ground-truth rows g, pair by pair.

    Pairs whose BEV IoU cannot exceed `floor` are reported as 0 without intersecting them: the
    evaluator passes the smallest class overlap, below which no value changes a result. The bound
    (intersection at most the smaller footprint and at most the overlap of the two axis-aligned
    boxes around the footprints) also bounds the 3D IoU, which never exceeds the BEV IoU.
    """
    bev, box3d = np.zeros(len(d)), np.zeros(len(d))
    if len(d) == 0:
        return bev, box3d
    cd = bev_corners(det.location[d], det.dims[d], det.rotation_y[d])
    cg = bev_corners(gt.location[g], gt.dims[g], gt.rotation_y[g])
    area_d = np.abs(det.dims[d, 1] * det.dims[d, 2])
    area_g = np.abs(gt.dims[g, 1] * gt.dims[g, 2])
    lo = np.maximum(cd.min(axis=1), cg.min(axis=1))
    hi = np.minimum(cd.max(axis=1), cg.max(axis=1))
    bound = np.minimum(np.prod(np.clip(hi - lo, 0, None), axis=1), np.minimum(area_d, area_g))
    union_bound = area_d + area_g - bound
    # a hair below the bound: pairs at the threshold itself are decided on GEOS's value, not this one
    hopeful = (bound > 0) & (bound > floor * union_bound * (1 - 1e-9))
    k = np.nonzero(hopeful)[0]
    if len(k) == 0:
        return bev, box3d
    inter = bev_intersection(cd[k], cg[k])
    union = area_d[k] + area_g[k] - inter
    bev_k = np.zeros(len(k))
    np.divide(inter, union, out=bev_k, where=union > 0)
    bev[k] = bev_k
    # y points down: a box spans [y - h, y]
    dk, gk = d[k], g[k]
    y_overlap = np.clip(np.minimum(det.location[dk, 1], gt.location[gk, 1])
                        - np.maximum(det.location[dk, 1] - det.dims[dk, 0], gt.location[gk, 1] - gt.dims[gk, 0]),
                        0, None)
    inter_v = inter * y_overlap
    union_v = det.dims[dk].prod(axis=1) + gt.dims[gk].prod(axis=1) - inter_v
    v_k = np.zeros(len(k))
    np.divide(inter_v, union_v, out=v_k, where=(union_v > 0) & (inter_v > 0))
    box3d[k] = v_k
    return bev, box3d


# ---------------------------------------------------------------------------------------------
# the evaluation
# ---------------------------------------------------------------------------------------------


@dataclass
class _Flat:
    """All frames' objects concatenated (frame order, then file order), with each row's frame."""

    labels: KittiLabels
    frame: np.ndarray  # (N,) frame index of each row
    start: np.ndarray  # (F,) first row of each frame
    count: np.ndarray  # (F,) rows per frame
    lower: np.ndarray  # (N,) lower-cased names

    @staticmethod
    def of(frames: Sequence[KittiLabels]) -> "_Flat":
        count = np.array([len(f) for f in frames], dtype=np.int64)
        start = np.concatenate([[0], np.cumsum(count)[:-1]]).astype(np.int64)
        cat = lambda attr: np.concatenate([getattr(f, attr) for f in frames]) if frames else np.zeros(0)  # noqa: E731
        labels = KittiLabels(names=cat("names").astype(str), truncated=cat("truncated"),
                             occluded=cat("occluded").astype(np.int64), alpha=cat("alpha"),
                             bbox=cat("bbox").reshape(-1, 4), dims=cat("dims").reshape(-1, 3),
                             location=cat("location").reshape(-1, 3), rotation_y=cat("rotation_y"),
                             score=cat("score").astype(np.float64))
        frame = np.repeat(np.arange(len(frames)), count)
        return _Flat(labels, frame, start, count, np.char.lower(labels.names))


def _frame_pairs(rows: np.ndarray, frame_of_rows: np.ndarray, other: _Flat) -> tuple[np.ndarray, np.ndarray]:
    """Every (row, other row) pair of the same frame, rows in order, then other rows in file order."""
    f = frame_of_rows[rows]
    k = other.count[f]
    a = np.repeat(rows, k)
    offset = np.arange(int(k.sum())) - np.repeat(np.cumsum(k) - k, k)
    b = np.repeat(other.start[f], k) + offset
    return a, b


@dataclass
class _Pairs:
    """Candidate (ground truth, detection) pairs of one frame each, with their overlap per metric."""

    gt: np.ndarray
    det: np.ndarray
    overlap: dict[str, np.ndarray]


def _pairs(gt: _Flat, det: _Flat, classes: Sequence[str]) -> _Pairs:
    """The pairs some class's evaluation looks at: an object of the class or its neighbour, with a
    detection of the class or one lower than the tallest minimum height (ignored detections of any
    class can be matched)."""
    names = [c.lower() for c in classes]
    family = {c: {c, NEIGHBOUR[c]} if c in NEIGHBOUR else {c} for c in names}
    gt_rows = np.nonzero(np.isin(gt.lower, sorted(set().union(*family.values()))))[0]
    g, d = _frame_pairs(gt_rows, gt.frame, det)
    b = det.labels.bbox
    keep = np.abs(b[d, 3] - b[d, 1]) < max(MIN_HEIGHT)
    for c in names:
        keep |= (det.lower[d] == c) & np.isin(gt.lower[g], sorted(family[c]))
    g, d = g[keep], d[keep]
    bev, box3d = bev_and_3d_overlaps(det.labels, gt.labels, d, g, floor=min(MIN_OVERLAP[c] for c in classes))
    return _Pairs(g, d, {"bbox": box2d_iou(det.labels.bbox[d], gt.labels.bbox[g]), "bev": bev, "3d": box3d})


def _dontcare_cover(gt: _Flat, det: _Flat) -> np.ndarray:
    """Per detection, the largest share of its 2D box inside one DontCare region of its frame."""
    cover = np.zeros(len(det.frame))
    dc_rows = np.nonzero(gt.lower == "dontcare")[0]
    g, d = _frame_pairs(dc_rows, gt.frame, det)
    if len(g):
        np.maximum.at(cover, d, box2d_iou(det.labels.bbox[d], gt.labels.bbox[g], criterion=0))
    return cover


def get_thresholds(scores: np.ndarray, num_gt: int, num_sample_pts: int = N_SAMPLE_PTS) -> np.ndarray:
    """Scores at which recall passes the sample positions i / (num_sample_pts - 1) (the devkit's rule).

    Walks the true-positive scores from the highest, keeping a score when its recall (i+1)/num_gt is
    at least as close to the next sample position as the following score's recall is.
    """
    v = np.sort(np.asarray(scores, dtype=np.float64))[::-1]
    out: list[float] = []
    current = 0.0
    n = len(v)
    for i in range(n):
        l_recall = (i + 1) / num_gt
        r_recall = (i + 2) / num_gt if i < n - 1 else l_recall
        if (r_recall - current) < (current - l_recall) and i < n - 1:
            continue
        out.append(float(v[i]))
        current += 1.0 / (num_sample_pts - 1.0)
    return np.array(out)


@dataclass
class _Problem:
    """One class at one difficulty: who is ignored, and the candidate pairs as padded arrays."""

    num_valid_gt: int
    ig_det: np.ndarray  # (Nd,) -1 not evaluated, 0 valid, 1 ignored (too low)
    ig_gt: np.ndarray  # (Ng,) -1 not evaluated, 0 valid, 1 ignored (difficulty or neighbour class)


def _ignore_flags(gt: _Flat, det: _Flat, cls: str, level: int) -> _Problem:
    name = cls.lower()
    b = gt.labels.bbox
    height = b[:, 3] - b[:, 1]
    outside = ((gt.labels.occluded > MAX_OCCLUSION[level]) | (gt.labels.truncated > MAX_TRUNCATION[level])
               | (height < MIN_HEIGHT[level]))
    own = gt.lower == name
    neighbour = gt.lower == NEIGHBOUR.get(name, "\0")
    ig_gt = np.full(len(own), -1, dtype=np.int8)
    ig_gt[own | neighbour] = 1
    ig_gt[own & ~outside] = 0
    db = det.labels.bbox
    low = np.abs(db[:, 3] - db[:, 1]) < MIN_HEIGHT[level]
    ig_det = np.full(len(db), -1, dtype=np.int8)
    ig_det[det.lower == name] = 0
    ig_det[low] = 1  # any class: the devkit tests the height before the class
    return _Problem(int(np.count_nonzero(ig_gt == 0)), ig_det, ig_gt)


@dataclass
class _Padded:
    """Candidate pairs packed per frame: rows sorted by how many ground-truth objects they hold."""

    overlap: np.ndarray  # (F, G, D) overlap of local gt i with local detection j (0 where no pair)
    gt_flag: np.ndarray  # (F, G) ig_gt of local gt i; -2 for padding
    det_flag: np.ndarray  # (F, D) ig_det of local detection j; -2 for padding
    score: np.ndarray  # (F, D)
    cover: np.ndarray  # (F, D) DontCare cover (2D only; zeros otherwise)
    rows_with: np.ndarray  # (G,) how many frames have more than i local gts


def _local_index(rows: np.ndarray, frame: np.ndarray, frame_row: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique sorted rows, and for each its position among its frame's rows (rows are frame-ordered)."""
    u = np.unique(rows)
    fu = frame_row[frame[u]]
    first = np.searchsorted(fu, fu, side="left") if len(u) else fu
    return u, np.arange(len(u)) - first


def _pack(gt_idx: np.ndarray, det_idx: np.ndarray, ov: np.ndarray, gt: _Flat, det: _Flat,
          prob: _Problem, cover: np.ndarray) -> _Padded:
    frames = np.unique(gt.frame[gt_idx])
    frame_row = np.full(len(gt.count), -1, dtype=np.int64)
    frame_row[frames] = np.arange(len(frames))
    ug, lg = _local_index(gt_idx, gt.frame, frame_row)
    ud, ld = _local_index(det_idx, det.frame, frame_row)
    n_g = np.bincount(frame_row[gt.frame[ug]], minlength=len(frames))
    order = np.argsort(-n_g, kind="stable")  # frames with most objects first: row slices shrink with i
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    F, G = len(frames), int(lg.max()) + 1 if len(lg) else 0
    D = int(ld.max()) + 1 if len(ld) else 0
    gt_flag = np.full((F, G), -2, dtype=np.int8)
    det_flag = np.full((F, D), -2, dtype=np.int8)
    score = np.zeros((F, D))
    cov = np.zeros((F, D))
    rg, rd = rank[frame_row[gt.frame[ug]]], rank[frame_row[det.frame[ud]]]
    gt_flag[rg, lg] = prob.ig_gt[ug]
    det_flag[rd, ld] = prob.ig_det[ud]
    score[rd, ld] = det.labels.score[ud]
    cov[rd, ld] = cover[ud]
    overlap = np.zeros((F, G, D))
    pg = np.searchsorted(ug, gt_idx)
    pd = np.searchsorted(ud, det_idx)
    overlap[rank[frame_row[gt.frame[gt_idx]]], lg[pg], ld[pd]] = ov
    rows_with = np.array([np.count_nonzero(n_g > i) for i in range(G)], dtype=np.int64)
    return _Padded(overlap, gt_flag, det_flag, score, cov, rows_with)


def _tp_scores(p: _Padded, min_overlap: float) -> np.ndarray:
    """Scores of the true positives when each object takes its highest-scored candidate (first pass)."""
    F, G, D = p.overlap.shape
    assigned = np.zeros((F, D), dtype=bool)
    usable = (p.det_flag >= 0) & (p.score > NO_DETECTION)
    found: list[np.ndarray] = []
    for i in range(G):
        n = p.rows_with[i]
        cand = usable[:n] & ~assigned[:n] & (p.overlap[:n, i] > min_overlap)
        has = cand.any(axis=1) & (p.gt_flag[:n, i] >= 0)
        j = np.argmax(np.where(cand, p.score[:n], -np.inf), axis=1)  # first of equal scores, as the loop
        r = np.nonzero(has)[0]
        jr = j[r]
        tp = (p.gt_flag[r, i] == 0) & (p.det_flag[r, jr] == 0)
        found.append(p.score[r[tp], jr[tp]])
        assigned[r, jr] = True
    return np.concatenate(found) if found else np.zeros(0)


def _counts_at(p: _Padded, min_overlap: float, thresholds: np.ndarray, use_cover: bool
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """TP, FP, FN of the packed pairs at every threshold (batched over thresholds)."""
    T = len(thresholds)
    F, G, D = p.overlap.shape
    active = (p.det_flag[None] >= 0) & (p.score[None] >= thresholds[:, None, None])  # (T, F, D)
    assigned = np.zeros((T, F, D), dtype=bool)
    tp = np.zeros(T, dtype=np.int64)
    fn = np.zeros(T, dtype=np.int64)
    valid_det = p.det_flag == 0
    low_det = p.det_flag == 1
    for i in range(G):
        n = p.rows_with[i]
        ov = p.overlap[None, :n, i]
        cand = active[:, :n] & ~assigned[:, :n] & (ov > min_overlap)
        cv = cand & valid_det[None, :n]
        ci = cand & low_det[None, :n]
        has_v = cv.any(axis=2)
        jv = np.argmax(np.where(cv, ov, -np.inf), axis=2)  # first greatest overlap, as the loop
        ji = np.argmax(ci, axis=2)  # first low detection, taken only when no valid one overlaps
        has = has_v | ci.any(axis=2)
        j = np.where(has_v, jv, ji)
        flag = p.gt_flag[:n, i][None]
        exists = flag >= 0
        has &= exists
        fn += np.count_nonzero(~has & (flag == 0), axis=1)
        tp += np.count_nonzero(has_v & exists & (flag == 0), axis=1)
        t, r = np.nonzero(has)
        assigned[t, r, j[t, r]] = True
    free = active & ~assigned & valid_det[None]
    if use_cover:
        free &= ~(p.cover[None] > min_overlap)
    fp = np.count_nonzero(free.reshape(T, -1), axis=1)
    return tp, fp, fn


def _average_precision(precision: np.ndarray) -> tuple[float, float]:
    """AP40 and AP11 in percent from the 41 monotone precision samples."""
    return float(precision[1:].sum() / 40 * 100), float(precision[0::4].sum() / 11 * 100)


def _evaluate_one(gt: _Flat, det: _Flat, pairs: _Pairs, cover: np.ndarray, cls: str, level: int, metric: str
                  ) -> tuple[float, float]:
    prob = _ignore_flags(gt, det, cls, level)
    if prob.num_valid_gt == 0:
        return 0.0, 0.0
    mo = MIN_OVERLAP[cls]
    ov = pairs.overlap[metric]
    keep = (ov > mo) & (prob.ig_gt[pairs.gt] >= 0) & (prob.ig_det[pairs.det] >= 0)
    gi, di, ok = pairs.gt[keep], pairs.det[keep], ov[keep]
    packed = _pack(gi, di, ok, gt, det, prob, cover if metric == "bbox" else np.zeros(len(cover)))
    thresholds = get_thresholds(_tp_scores(packed, mo), prob.num_valid_gt)
    if len(thresholds) == 0:
        return 0.0, 0.0
    # Objects and detections outside every candidate pair: never matched, counted directly.
    linked_gt = np.zeros(len(prob.ig_gt), dtype=bool)
    linked_gt[gi] = True
    linked_det = np.zeros(len(prob.ig_det), dtype=bool)
    linked_det[di] = True
    lone_fn = np.count_nonzero((prob.ig_gt == 0) & ~linked_gt)
    lone = (prob.ig_det == 0) & ~linked_det
    if metric == "bbox":
        lone &= ~(cover > mo)
    lone_scores = np.sort(det.labels.score[lone])
    lone_fp = len(lone_scores) - np.searchsorted(lone_scores, thresholds, side="left")  # score >= t
    tp, fp, fn = _counts_at(packed, mo, thresholds, metric == "bbox")
    fp = fp + lone_fp
    fn = fn + lone_fn
    precision = np.zeros(N_SAMPLE_PTS)
    denom = tp + fp
    precision[:len(thresholds)] = np.divide(tp, denom, out=np.zeros(len(tp)), where=denom > 0)
    precision = np.maximum.accumulate(precision[::-1])[::-1]
    return _average_precision(precision)


def evaluate(gt_frames: Sequence[KittiLabels], pred_frames: Sequence[KittiLabels],
             classes: Sequence[str] = CLASSES) -> dict:
    """KITTI AP in percent: {"AP40": {cls: {"bbox": [easy, moderate, hard], "bev": [...], "3d": [...]}},
    "AP11": {...}}, frames paired by position."""
    if len(gt_frames) != len(pred_frames):
        raise ValueError(f"{len(gt_frames)} ground-truth frames but {len(pred_frames)} prediction frames")
    for cls in classes:
        if cls not in MIN_OVERLAP:
            raise ValueError(f"class {cls!r} has no KITTI overlap threshold; known: {', '.join(MIN_OVERLAP)}")
    gt, det = _Flat.of(gt_frames), _Flat.of(pred_frames)
    pairs = _pairs(gt, det, classes)
    cover = _dontcare_cover(gt, det)
    result: dict = {"AP40": {}, "AP11": {}}
    for cls in classes:
        result["AP40"][cls] = {}
        result["AP11"][cls] = {}
        for metric in METRICS:
            ap = [_evaluate_one(gt, det, pairs, cover, cls, level, metric) for level in range(len(DIFFICULTIES))]
            result["AP40"][cls][metric] = [a40 for a40, _ in ap]
            result["AP11"][cls][metric] = [a11 for _, a11 in ap]
    return result
