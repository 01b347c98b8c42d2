"""Keypoint metrics of predictions on an UrbanOmniView dataset: OKS mAP, AP50, best-F1 P/R, adherence.

The matching is pycocotools' own (COCOeval, iouType='keypoints'): OKS with sigma 0.125 on all eight
box corners, corners outside the image (v = 0) ignored, objects without any corner in the image
ignored (COCO's num_keypoints == 0 rule; a detection of such an object is forgiven only when its
corners fall inside twice the object's clipped 2D box, else it counts as a false positive).
Predictions are the COCO-results list; frame_id, when present, names the image (else image_id,
omnigen.formats.coco's 1-based frame order); predictions on frames outside the split are left out and
counted. Choices, and why:

- maxDets = [MAX_DETS] (1000) and one area range ('all'). A drone view of a crowded junction holds
  hundreds of objects; COCO's 20 would cut recall. pycocotools' summarize() hard-codes maxDets 20
  and the medium/large ranges, so the numbers here are read from eval['precision'] directly:
  mAP50:95 is the mean of the valid (> -1) precisions over the ten OKS thresholds, the 101 recall
  thresholds and the categories that have ground truth, exactly as summarize() would average them.
- evaluate() runs once over all evaluated images. Each group (overall, per source, per view) is
  an accumulate() over the group's slice of the per-image results (evalImgs), which is exact:
  pycocotools' accumulate only concatenates per-image results, so running it on a slice gives what
  a separate COCOeval restricted to those images (params.imgIds) gives, without re-matching.
- Per class ('class=car'), over the whole split: the same accumulate() over the class's slice of
  evalImgs (pycocotools' params.catIds = [class]). mAP50:95 is the mean of these rows, so one
  class the model misses costs as much as cars do; the rows show which. Classes without ground
  truth in the split get no row (and do not enter the mean).
- Precision, recall and F1 are micro-averaged over classes at OKS 0.5: every non-ignored detection
  of the group (class-aware matches, as in AP) is pooled and sorted by score; the threshold is
  swept only between distinct scores (a threshold keeps every detection scoring >= it), and the
  one with the highest F1 is reported (the highest such threshold on ties).
- `objects` counts the non-ignored ground truth (at least one corner in the image): the recall's
  denominator.
- Per object size ('size=tiny', ..., over the whole split): pycocotools' own area ranges, as its
  small/medium/large are made, in a second COCOeval over the same matching inputs: ground truth
  outside the range is ignored, and so is an unmatched detection outside it. The bins (SIZE_BINS,
  in sqrt of the 2D box area) split COCO's 'small' at 16 px because most objects of a 640-pixel
  drone or pole view are smaller than 32 px, and those are what the stride-4 P2 level is for.
- Ground-plane adherence (the mean angle between a lifted predicted box's ground-contact edges and
  the true ground plane): for predictions matched to non-ignored ground truth at OKS >= 0.5 in
  frames whose ground plane is known. Each is lifted to 3D from its eight predicted corners, the
  frame's intrinsics and the class dimension prior of the matched object's fine class (the
  prediction's own class under the fine taxonomy; its refinement under coarser ones). Priors come
  from the dataset's 'train' split when it has one, else from all frames (report.priors_from).
  Lifts that fail (ok = False) are left out and counted.
- Corner errors (corner_error_px, corner_error_rel; per corner with per_corner=True): medians of
  the distances between predicted and true corners of the objects matched to a prediction by 2D
  box IoU >= 0.5, not by OKS, over their labelled corners (detector/evaluation/corner_errors.py says why).
  Per source, view and class the group's objects; per size, the objects whose box is in the bin.
"""

from __future__ import annotations

import contextlib
import copy
import io
import math
from collections import defaultdict
from dataclasses import asdict, dataclass, field
from typing import Any, Iterable, Sequence

import numpy as np
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

from omnigen.detector.evaluation.corner_errors import BOX_MATCH_IOU, CornerErrors, corners_extent_boxes, matched_corners
from omnigen.formats.coco import to_coco
from omnigen.conventions import NUM_KEYPOINTS
from omnigen.dataset import Dataset
from omnigen.splits import TRAIN, read_split, split_names
from omnigen.taxonomy import Taxonomy, load_taxonomy

OKS_SIGMA = 0.125
MAX_DETS = 1000
AREA_ALL = [0.0, 1e5 ** 2]  # pycocotools' 'all' range
# object size bins: name -> (lower, upper) sqrt of the 2D box area in pixels (pycocotools compares areas)
SIZE_BINS = {"tiny": (0.0, 16.0), "small": (16.0, 32.0), "medium": (32.0, 96.0), "large": (96.0, 1e5)}


class PredictionError(ValueError):
    """A prediction that cannot be evaluated; the message names the file, the prediction and the field."""


@dataclass
class EvalRow:
    group: str  # 'overall', 'source=kitti', 'view=aerial', 'class=car' (images: those with the class), ...
    images: int
    objects: int  # non-ignored ground truth
    oks_map50_95: float
    ap_oks50: float
    precision: float  # at OKS 0.5 and conf_threshold
    recall: float
    f1: float
    conf_threshold: float
    ground_adherence_deg: float = math.nan  # NaN where no matched prediction has a known ground plane
    adherence_objects: int = 0
    # medians over the labelled corners of the box-matched objects (detector/evaluation/corner_errors.py); NaN: none
    corner_error_px: float = math.nan
    corner_error_rel: float = math.nan  # each corner's error / sqrt(the object's 2D box area)
    corner_objects: int = 0  # box-matched objects with a labelled corner
    corner_spread: float = math.nan  # median predicted / true corner spread (corner_errors.spread_ratio)
    layout_error_rel: float = math.nan  # corner_error_rel up to the 180-degree turn (corner_errors)
    corner_errors_per_corner: list[float] | None = None  # px medians per corner 0..7 (per_corner=True)
    corner_errors_rel_per_corner: list[float] | None = None


@dataclass
class EvalReport:
    rows: list[EvalRow]
    split: str | None
    taxonomy: str
    predictions: int  # evaluated (inside the split)
    predictions_outside_split: int  # valid frames of the dataset outside the split: left out
    max_dets: int = MAX_DETS
    oks_sigma: float = OKS_SIGMA
    priors_from: str | None = None  # 'train' or 'all frames'; None when adherence was not computed
    lift_failures: int = 0
    box_match_iou: float = BOX_MATCH_IOU  # the corner errors' matching
    notes: list[str] = field(default_factory=list)

    def row(self, group: str) -> EvalRow:
        for r in self.rows:
            if r.group == group:
                return r
        raise KeyError(group)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready: NaN (undefined metric) becomes None."""
        return _nan_to_none(asdict(self))


def _nan_to_none(obj: Any) -> Any:
    if isinstance(obj, float):
        return None if math.isnan(obj) else obj
    if isinstance(obj, dict):
        return {k: _nan_to_none(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_nan_to_none(v) for v in obj]
    return obj


# ---------------------------------------------------------------------------------------------
# Predictions
# ---------------------------------------------------------------------------------------------


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def normalize_predictions(predictions: Sequence[dict[str, Any]], ds: Dataset, image_ids: set[int],
                          n_categories: int, source: str = "<predictions>") -> tuple[list[dict[str, Any]], int]:
    """Checked copies {image_id, category_id, keypoints, score, pred_box} of the predictions inside the split.

    pred_box is the prediction's bbox as x1 y1 x2 y2, None when it has none (the corner errors'
    box matching then uses its corners' extent).

    frame_id wins over image_id when both are given (image ids are positions in one dataset's
    frame order, frame ids survive re-merging). A frame of the dataset outside the evaluated split
    is left out and counted; an id the dataset does not know is an error.
    """
    out: list[dict[str, Any]] = []
    rows: list[int] = []  # position of each kept prediction in the input, for error messages
    outside = 0
    if not isinstance(predictions, list):
        raise PredictionError(f"{source}: expected a JSON list of predictions (COCO results form)")
    for i, p in enumerate(predictions):
        where = f"{source}: prediction {i}"
        if not isinstance(p, dict):
            raise PredictionError(f"{where}: expected an object")
        if p.get("frame_id") is not None:
            fid = p["frame_id"]
            try:
                image_id = ds.index_of(str(fid)) + 1
            except KeyError:
                raise PredictionError(f"{where}: field 'frame_id': no frame {fid!r} in {ds.root}") from None
        elif "image_id" in p:
            image_id = p["image_id"]
            if not isinstance(image_id, int) or isinstance(image_id, bool) or not 1 <= image_id <= len(ds):
                raise PredictionError(f"{where}: field 'image_id': unknown image id {image_id!r} "
                                      f"(ids are 1..{len(ds)}, the dataset's frame order)")
        else:
            raise PredictionError(f"{where}: field 'image_id': missing (give image_id or frame_id)")
        kp = p.get("keypoints")
        if kp is None:
            raise PredictionError(f"{where}: field 'keypoints': missing")
        if not isinstance(kp, list) or len(kp) != 3 * NUM_KEYPOINTS:
            got = len(kp) if isinstance(kp, list) else type(kp).__name__
            raise PredictionError(f"{where}: field 'keypoints': expected {3 * NUM_KEYPOINTS} numbers "
                                  f"(x, y, v per corner), got {got}")
        cat = p.get("category_id")
        if not isinstance(cat, int) or isinstance(cat, bool) or not 1 <= cat <= n_categories:
            raise PredictionError(f"{where}: field 'category_id': {cat!r} is not a category id 1..{n_categories}")
        score = p.get("score")
        if not _is_number(score):
            raise PredictionError(f"{where}: field 'score': missing or not a finite number")
        box = p.get("bbox")
        if box is not None and not (isinstance(box, list) and len(box) == 4 and all(_is_number(v) for v in box)
                                    and box[2] >= 0 and box[3] >= 0):
            raise PredictionError(f"{where}: field 'bbox': expected x, y, w, h (four finite numbers, w and h >= 0)")
        if image_id not in image_ids:
            outside += 1
            continue
        out.append({"image_id": image_id, "category_id": cat, "keypoints": kp, "score": float(score),
                    "pred_box": None if box is None else [box[0], box[1], box[0] + box[2], box[1] + box[3]]})
        rows.append(i)
    _check_keypoint_values(out, rows, source)
    return out, outside


def _check_keypoint_values(out: list[dict[str, Any]], rows: list[int], source: str) -> None:
    """All keypoint values finite numbers, checked at once (two million values per 80,000 predictions)."""
    try:
        values = np.array([a["keypoints"] for a in out], dtype=np.float64).reshape(len(out), 3 * NUM_KEYPOINTS)
        bad = np.flatnonzero(~np.isfinite(values).all(axis=1))
    except (TypeError, ValueError):
        values = None
        bad = [n for n, a in enumerate(out) if not all(_is_number(v) for v in a["keypoints"])]
    if len(bad):
        raise PredictionError(f"{source}: prediction {rows[bad[0]]}: field 'keypoints': not all finite numbers")
    for a, v in zip(out, values.tolist()):
        a["keypoints"] = v  # plain floats, a copy: pycocotools never touches the caller's lists


def _results_coco(gt: COCO, anns: list[dict[str, Any]]) -> COCO:
    """The detections as a COCO object, as COCO.loadRes builds it for keypoints.

    Same ids (1-based order), bbox and area (the extent of all corners); built directly so that an
    empty prediction list works and nothing is printed.
    """
    if anns:
        xy = np.asarray([a["keypoints"] for a in anns], dtype=np.float64).reshape(len(anns), NUM_KEYPOINTS, 3)
        lo, hi = xy[:, :, :2].min(axis=1), xy[:, :, :2].max(axis=1)
        wh = hi - lo
        for i, a in enumerate(anns):
            a["id"] = i + 1
            a["bbox"] = [float(lo[i, 0]), float(lo[i, 1]), float(wh[i, 0]), float(wh[i, 1])]
            a["area"] = float(wh[i, 0] * wh[i, 1])
    res = COCO()
    res.dataset = {"images": list(gt.dataset["images"]), "categories": copy.deepcopy(gt.dataset["categories"]),
                   "annotations": anns}
    with contextlib.redirect_stdout(io.StringIO()):
        res.createIndex()
    return res


def _coco_from_dict(d: dict[str, Any]) -> COCO:
    c = COCO()
    c.dataset = d
    with contextlib.redirect_stdout(io.StringIO()):
        c.createIndex()
    return c


# ---------------------------------------------------------------------------------------------
# Matching once, accumulating per group
# ---------------------------------------------------------------------------------------------


class KeypointEval(COCOeval):
    """COCOeval that skips the (image, category) pairs with nothing to compare before sorting.

    pycocotools visits every image for every category (120,000 pairs for 10,000 frames and 12
    classes, most of them empty) and sorts the detections before noticing that a side is empty.
    Returning the same [] first changes no number and saves seconds. The per-size evaluation
    matches the same objects and predictions under other area ranges; the OKS between them does
    not depend on the range, so it takes them from the first evaluation (`known_oks`).
    """

    known_oks: dict | None = None  # another evaluation's ious over the same gt, dt and maxDets: reused

    def computeOks(self, imgId, catId):  # noqa: N802 (pycocotools' name)
        if not self._gts[imgId, catId] or not self._dts[imgId, catId]:
            return []
        if self.known_oks is not None:
            return self.known_oks[imgId, catId]
        return super().computeOks(imgId, catId)


def make_cocoeval(gt: COCO, dt: COCO, img_ids: Iterable[int] | None = None) -> COCOeval:
    """COCOeval with this module's parameters (sigma, maxDets, one area range)."""
    e = KeypointEval(gt, dt, iouType="keypoints")
    e.params.kpt_oks_sigmas = np.full(NUM_KEYPOINTS, OKS_SIGMA)
    e.params.maxDets = [MAX_DETS]
    e.params.areaRng = [list(AREA_ALL)]
    e.params.areaRngLbl = ["all"]
    e.params.imgIds = sorted(gt.getImgIds()) if img_ids is None else sorted(img_ids)
    return e


def make_size_cocoeval(gt: COCO, dt: COCO) -> COCOeval:
    """make_cocoeval with one area range per SIZE_BINS entry instead of 'all'."""
    e = make_cocoeval(gt, dt)
    e.params.areaRng = [[lo ** 2, hi ** 2] for lo, hi in SIZE_BINS.values()]
    e.params.areaRngLbl = list(SIZE_BINS)
    return e


def run_quietly(fn, *args):
    with contextlib.redirect_stdout(io.StringIO()):
        return fn(*args)


def _sliced(e: COCOeval, sub_imgs: list, **params: Any) -> tuple[list, COCOeval]:
    """A shallow COCOeval over `sub_imgs` (a slice of e.evalImgs) with `params` narrowed to match."""
    sub = copy.copy(e)
    sub._paramsEval = copy.copy(e._paramsEval)
    for name, value in params.items():
        setattr(sub._paramsEval, name, value)
    sub.params = copy.copy(sub._paramsEval)
    sub.evalImgs = sub_imgs
    return sub_imgs, sub


def evalimgs_subset(e: COCOeval, img_ids: Iterable[int]) -> tuple[list, COCOeval]:
    """A shallow COCOeval whose evalImgs and parameters cover only `img_ids` (already evaluated)."""
    pe = e._paramsEval
    pos = {int(i): n for n, i in enumerate(pe.imgIds)}
    keep = sorted(pos[int(i)] for i in img_ids)
    n_img, n_area = len(pe.imgIds), len(pe.areaRng)
    sub_imgs = [e.evalImgs[k * n_area * n_img + a * n_img + i]
                for k in range(len(pe.catIds)) for a in range(n_area) for i in keep]
    return _sliced(e, sub_imgs, imgIds=[pe.imgIds[i] for i in keep])


def evalimgs_category(e: COCOeval, k: int) -> tuple[list, COCOeval]:
    """A shallow COCOeval whose evalImgs and parameters cover only the k-th category (evaluated)."""
    pe = e._paramsEval
    n_img, n_area = len(pe.imgIds), len(pe.areaRng)
    return _sliced(e, e.evalImgs[k * n_area * n_img:(k + 1) * n_area * n_img], catIds=[pe.catIds[k]])


def evalimgs_area(e: COCOeval, a: int) -> tuple[list, COCOeval]:
    """A shallow COCOeval whose evalImgs and parameters cover only the a-th area range (evaluated)."""
    pe = e._paramsEval
    n_img, n_area = len(pe.imgIds), len(pe.areaRng)
    sub_imgs = [e.evalImgs[k * n_area * n_img + a * n_img + i] for k in range(len(pe.catIds)) for i in range(n_img)]
    return _sliced(e, sub_imgs, areaRng=[pe.areaRng[a]])


def ap_numbers(precision: np.ndarray) -> tuple[float, float]:
    """mAP over OKS 0.50:0.95 and AP at OKS 0.50 from eval['precision'] (T, R, K, A=1, M=1)."""
    s = precision[:, :, :, 0, -1]
    valid = s[s > -1]
    s50 = s[0][s[0] > -1]
    return (float(valid.mean()) if valid.size else math.nan, float(s50.mean()) if s50.size else math.nan)


@dataclass
class Matches:
    """The per-image matching at one OKS threshold, flattened over images and categories.

    Detections beyond maxDets were already dropped by evaluateImg. `det_counted` is False for
    detections matched to ignored ground truth (neither true nor false positives);
    `det_match` is the matched ground-truth id (0: unmatched).
    """

    det_image: np.ndarray
    det_id: np.ndarray
    det_score: np.ndarray
    det_match: np.ndarray
    det_counted: np.ndarray
    gt_image: np.ndarray  # one entry per non-ignored ground truth

    @classmethod
    def from_eval_imgs(cls, eval_imgs: Iterable[dict | None], t: int = 0) -> "Matches":
        img, ids, score, match, counted, gt_img = [], [], [], [], [], []
        for r in eval_imgs:
            if r is None:
                continue
            n_dt = len(r["dtIds"])
            img.append(np.full(n_dt, r["image_id"], dtype=np.int64))
            ids.append(r["dtIds"])
            score.append(r["dtScores"])
            match.append(r["dtMatches"][t])
            counted.append(r["dtIgnore"][t])
            gt_img.append(np.full(int(np.count_nonzero(r["gtIgnore"] == 0)), r["image_id"], dtype=np.int64))

        def cat(parts: list, dtype: Any) -> np.ndarray:
            return np.concatenate([np.asarray(x, dtype=dtype) for x in parts]) if parts else np.zeros(0, dtype)

        return cls(cat(img, np.int64), cat(ids, np.int64), cat(score, np.float64), cat(match, np.int64),
                   ~cat(counted, bool), cat(gt_img, np.int64))

    def subset(self, img_ids: Iterable[int]) -> "Matches":
        ids = np.fromiter(img_ids, dtype=np.int64)
        d, g = np.isin(self.det_image, ids), np.isin(self.gt_image, ids)
        return Matches(self.det_image[d], self.det_id[d], self.det_score[d], self.det_match[d],
                       self.det_counted[d], self.gt_image[g])

    def matched_ids(self) -> dict[int, int]:
        """detection id -> ground-truth id, for detections matched to non-ignored ground truth."""
        m = (self.det_match > 0) & self.det_counted
        return dict(zip(self.det_id[m].tolist(), self.det_match[m].tolist()))


@dataclass
class BestF1:
    precision: float
    recall: float
    f1: float
    conf_threshold: float
    objects: int


def best_f1(matches: Matches | Iterable[dict | None]) -> BestF1:
    """Precision, recall and F1 at the score threshold maximising F1 (micro-averaged over classes)."""
    if not isinstance(matches, Matches):
        matches = Matches.from_eval_imgs(matches)
    n_gt = len(matches.gt_image)
    c = matches.det_counted
    s, is_tp = matches.det_score[c], matches.det_match[c] > 0
    if s.size == 0:
        return BestF1(math.nan, 0.0 if n_gt else math.nan, 0.0 if n_gt else math.nan, math.nan, n_gt)
    order = np.argsort(-s, kind="mergesort")
    s, is_tp = s[order], is_tp[order]
    tp, fp = np.cumsum(is_tp), np.cumsum(~is_tp)
    cut = np.flatnonzero(np.append(s[1:] != s[:-1], True))  # last detection of each distinct score
    tp, fp, s = tp[cut].astype(float), fp[cut].astype(float), s[cut]
    p = tp / (tp + fp)
    if n_gt == 0:
        return BestF1(float(p[-1]), math.nan, math.nan, float(s[-1]), 0)
    r = tp / n_gt
    with np.errstate(invalid="ignore", divide="ignore"):
        f1 = np.where(p + r > 0, 2 * p * r / (p + r), 0.0)
    best = int(np.argmax(f1))  # first maximum: the highest threshold among equals
    return BestF1(float(p[best]), float(r[best]), float(f1[best]), float(s[best]), n_gt)


# ---------------------------------------------------------------------------------------------
# Ground-plane adherence
# ---------------------------------------------------------------------------------------------


def adherence_per_detection(ds: Dataset, gt: COCO, anns: list[dict[str, Any]], matches: dict[int, int],
                            ) -> tuple[dict[int, float], str, int]:
    """detection id -> adherence in degrees, for matched detections in frames with a known ground plane.

    Returns also where the dimension priors came from and how many lifts failed.
    """
    from omnigen.detector.bev.lift import fit_dimension_priors, ground_adherence_deg, lift_keypoints

    planes = ds.table.ground_plane
    has_plane = np.isfinite(planes).all(axis=1)
    wanted = [d for d in matches if has_plane[anns[d - 1]["image_id"] - 1]]
    if not wanted:
        return {}, "", 0
    if TRAIN in split_names(ds.root):
        priors, priors_from = fit_dimension_priors(ds, read_split(ds.root, TRAIN)), TRAIN
    else:
        priors, priors_from = fit_dimension_priors(ds, list(ds.table.frame_id)), "all frames"
    by_frame: dict[int, list[int]] = defaultdict(list)
    for d in wanted:
        by_frame[anns[d - 1]["image_id"] - 1].append(d)
    out: dict[int, float] = {}
    failures = 0
    for frame, dets in by_frame.items():
        kps = np.asarray([anns[d - 1]["keypoints"] for d in dets], dtype=np.float64)
        kps = kps.reshape(len(dets), NUM_KEYPOINTS, 3)
        valid = ~(kps == 0).all(axis=2)  # corners written 0 0 0 are absent, not at pixel (0, 0)
        names = [gt.anns[matches[d]]["fine_category"] for d in dets]
        lifted = lift_keypoints(kps[:, :, :2], priors.dims_for(names), ds.table.K[frame], valid=valid)
        angles = np.asarray(ground_adherence_deg(lifted, planes[frame]), dtype=np.float64)
        ok = np.asarray(lifted.ok, bool) & np.isfinite(angles)
        failures += int((~ok).sum())
        for d, a, k in zip(dets, angles.tolist(), ok.tolist()):
            if k:
                out[d] = a
    return out, priors_from, failures


# ---------------------------------------------------------------------------------------------
# The evaluation
# ---------------------------------------------------------------------------------------------


def _row(name: str, images: int, sub_imgs: list, sub: COCOeval, group: Matches,
         angles: dict[int, float]) -> EvalRow:
    """One row of the report from a group's slice of the evaluation and of the matches (no corner errors)."""
    if any(r is not None for r in sub_imgs):
        run_quietly(sub.accumulate)
        m, ap50 = ap_numbers(sub.eval["precision"])
    else:
        m, ap50 = math.nan, math.nan
    f = best_f1(group)
    group_angles = [angles[d] for d in group.matched_ids() if d in angles]
    return EvalRow(group=name, images=images, objects=f.objects, oks_map50_95=m, ap_oks50=ap50,
                   precision=f.precision, recall=f.recall, f1=f.f1, conf_threshold=f.conf_threshold,
                   ground_adherence_deg=float(np.mean(group_angles)) if group_angles else math.nan,
                   adherence_objects=len(group_angles))


@dataclass
class Matched:
    """Predictions matched to the ground truth as evaluate matches them: the split's COCO ground
    truth (`gt_dict` and pycocotools' `gt`), the predictions normalised (`anns`, detection id i + 1
    is anns[i]), how many fell on frames outside the split, and the evaluation `e` (evaluated)."""

    gt_dict: dict[str, Any]
    gt: COCO
    dt: COCO
    anns: list[dict[str, Any]]
    outside: int
    e: COCOeval

    def matches(self) -> Matches:
        """The matching at OKS 0.5 (ground-plane adherence and F1 are of these matches)."""
        return Matches.from_eval_imgs(self.e.evalImgs)


def match_predictions(ds: Dataset, predictions: Sequence[dict[str, Any]], split: str | None = None,
                      taxonomy: Taxonomy | str = "fine", source: str = "<predictions>") -> Matched:
    """COCO-results predictions normalised and matched to `split` of `ds` by OKS (evaluate's first
    step; public so that a caller can read the matches)."""
    taxonomy = load_taxonomy(taxonomy) if isinstance(taxonomy, str) else taxonomy
    gt_dict = to_coco(ds, split, taxonomy)
    image_ids = {im["id"] for im in gt_dict["images"]}
    anns, outside = normalize_predictions(predictions, ds, image_ids, len(gt_dict["categories"]), source)
    gt = _coco_from_dict(gt_dict)
    dt = _results_coco(gt, anns)
    e = make_cocoeval(gt, dt)
    run_quietly(e.evaluate)
    return Matched(gt_dict, gt, dt, anns, outside, e)


def evaluate(ds: Dataset, predictions: Sequence[dict[str, Any]], split: str | None = None,
             taxonomy: Taxonomy | str = "fine", adherence: bool = True,
             source: str = "<predictions>", sizes: bool = True, per_corner: bool = False) -> EvalReport:
    """Evaluate COCO-results predictions on `split` of `ds` (None: all frames): overall, per source,
    view and class, and (`sizes`) per object size; `per_corner` adds each row's medians per corner."""
    taxonomy = load_taxonomy(taxonomy) if isinstance(taxonomy, str) else taxonomy
    m = match_predictions(ds, predictions, split, taxonomy, source)
    gt_dict, gt, dt, anns, outside, e = m.gt_dict, m.gt, m.dt, m.anns, m.outside, m.e
    image_ids = {im["id"] for im in gt_dict["images"]}

    groups: dict[str, list[int]] = {"overall": sorted(image_ids)}
    for key in ("source", "view"):
        members: dict[str, list[int]] = defaultdict(list)
        for im in gt_dict["images"]:
            members[im[key]].append(im["id"])
        for name in sorted(members):
            groups[f"{key}={name}"] = members[name]

    report = EvalReport(rows=[], split=split, taxonomy=taxonomy.name, predictions=len(anns),
                        predictions_outside_split=outside)
    matches = m.matches()  # at OKS 0.5
    angles: dict[int, float] = {}
    if adherence and anns:
        try:
            angles, priors_from, report.lift_failures = adherence_per_detection(ds, gt, anns, matches.matched_ids())
            report.priors_from = priors_from or None
        except ModuleNotFoundError as exc:
            if exc.name != "omnigen.detector.bev.lift":
                raise
            report.notes.append("ground-plane adherence not computed: omnigen.detector.bev.lift is not installed")
    for name, ids in groups.items():
        sub_imgs, sub = evalimgs_subset(e, ids)
        report.rows.append(_row(name, len(ids), sub_imgs, sub, matches.subset(ids), angles))
    # Per class over the whole split: mAP is the mean of these, so a rare class the model misses
    # weighs as much as cars do; classes without ground truth in the split are left out (as in
    # pycocotools' mean).
    names = {c["id"]: c["name"] for c in gt_dict["categories"]}
    for k, cat_id in enumerate(e._paramsEval.catIds):
        sub_imgs, sub = evalimgs_category(e, k)
        group = Matches.from_eval_imgs(sub_imgs)
        if len(group.gt_image):
            report.rows.append(_row(f"class={names[cat_id]}", len(np.unique(group.gt_image)), sub_imgs, sub,
                                    group, angles))
    if sizes:
        report.rows += _size_rows(gt, dt, angles, e.ious)
    corners = _corner_errors_by_group(ds, gt_dict, anns)
    for row in report.rows:
        _set_corner_errors(row, corners.get(row.group), per_corner)
    if outside:
        report.notes.append(f"{outside} predictions on frames outside split {split!r} were left out")
    if report.lift_failures:
        report.notes.append(f"{report.lift_failures} matched predictions could not be lifted to 3D "
                            f"(left out of the ground-plane adherence)")
    return report


def _size_rows(gt: COCO, dt: COCO, angles: dict[int, float], known_oks: dict | None = None) -> list[EvalRow]:
    """One row per SIZE_BINS entry that holds ground truth, over every evaluated image."""
    e = make_size_cocoeval(gt, dt)
    e.known_oks = known_oks
    run_quietly(e.evaluate)
    rows = []
    for a, name in enumerate(SIZE_BINS):
        sub_imgs, sub = evalimgs_area(e, a)
        group = Matches.from_eval_imgs(sub_imgs)
        if len(group.gt_image):
            rows.append(_row(f"size={name}", len(np.unique(group.gt_image)), sub_imgs, sub, group, angles))
    return rows


def _corner_errors_by_group(ds: Dataset, gt_dict: dict[str, Any], anns: list[dict[str, Any]]) -> dict[str, CornerErrors]:
    """Box-matched corner errors of every report group, keyed by the row's group name."""
    if anns:
        kp = np.asarray([a["keypoints"] for a in anns], dtype=np.float64).reshape(len(anns), NUM_KEYPOINTS, 3)
        frames = np.fromiter((a["image_id"] for a in anns), np.int64, len(anns)) - 1
        boxes = corners_extent_boxes(kp, ds.table.width[frames], ds.table.height[frames])
        given = [i for i, a in enumerate(anns) if a["pred_box"] is not None]
        if given:
            boxes[given] = np.asarray([anns[i]["pred_box"] for i in given], dtype=np.float64)
    else:
        boxes = np.zeros((0, 4))
    gt_anns = gt_dict["annotations"]
    mc = matched_corners(gt_anns, anns, boxes, max_dets=MAX_DETS)
    images = {im["id"]: im for im in gt_dict["images"]}
    matched = [gt_anns[i] for i in mc.gt_index.tolist()]
    out = {"overall": mc.summary()}
    for key in ("source", "view"):
        values = np.asarray([images[a["image_id"]][key] for a in matched], dtype=object)
        for name in np.unique(values).tolist():
            out[f"{key}={name}"] = mc.summary(values == name)
    names = {c["id"]: c["name"] for c in gt_dict["categories"]}
    cats = np.fromiter((a["category_id"] for a in matched), np.int64, len(matched))
    for cat_id in np.unique(cats).tolist():
        out[f"class={names[cat_id]}"] = mc.summary(cats == cat_id)
    size = np.sqrt(np.fromiter((a["area"] for a in matched), np.float64, len(matched)))
    for name, (lo, hi) in SIZE_BINS.items():  # inclusive at both ends, as pycocotools' area ranges
        out[f"size={name}"] = mc.summary((size >= lo) & (size <= hi))
    return out


def _set_corner_errors(row: EvalRow, c: CornerErrors | None, per_corner: bool) -> None:
    """A row's corner fields; a group without box-matched objects keeps NaN (and NaN per corner)."""
    c = c or CornerErrors.none()
    row.corner_error_px, row.corner_error_rel, row.corner_objects = c.px, c.rel, c.objects
    row.corner_spread, row.layout_error_rel = c.spread, c.layout_rel
    if per_corner:
        row.corner_errors_per_corner, row.corner_errors_rel_per_corner = c.per_corner_px, c.per_corner_rel
