"""The box-template baseline: each predicted 2D box's corners placed by a mean layout, no image needed.

A detector's corners are worth something only where they beat what its 2D box already implies.
The box implies a lot: a car seen by an ego camera has its bottom corners near the box's bottom
edge and its near face spanning most of its width, whatever the car. This baseline keeps each
prediction's box, class and score and replaces its eight corners by the **mean normalized corner
layout** of the prediction's class in the frame's view (ego, infrastructure, aerial, ...), learned
from the training split: corner (x, y) written as ((x - cx) / w, (y - cy) / h) relative to the
object's 2D box (centre cx, cy; size w, h). Scored by the same evaluation as the model
(omnigen.detector.evaluation.oks_eval), it is the bar the keypoint branch must clear: equal numbers mean the corners
carry no more than the box.

- Fitted from the dataset's 'train' split when it has one, else from all frames (and the report
  says so): never from the evaluated split alone, which would hand the baseline the answer.
- Every object with a 2D box of positive width and height contributes its corners that are in
  front of the camera (finite); corners outside the image are finite and kept, since the mean
  layout is about the box's shape, not about what is visible.
- The mean is taken per corner at three levels: the (class, view) pair, the class over all views,
  all objects. Each corner of a (class, view) uses the most specific level at which at least
  `min_objects` objects had that corner, so a rare pair falls back to its class and a rare class
  to the overall layout (a level with no object at all: the box centre).
- The layout is a mean, not a median, of each coordinate: the corner order is defined by the
  object's heading, and the mean over headings is the box-only answer in the least-squares sense.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np

from omnigen.detector.evaluation.oks_eval import EvalReport, PredictionError, evaluate
from omnigen.conventions import NUM_KEYPOINTS
from omnigen.dataset import Dataset
from omnigen.splits import TRAIN, read_split, split_names
from omnigen.taxonomy import Taxonomy, load_taxonomy

MIN_OBJECTS = 10
BASELINE_VISIBILITY = 1.0  # the v written for every placed corner (OKS ignores a prediction's v)


@dataclass
class Layout:
    """A mean normalized corner layout and how many objects each corner's mean is over."""

    corners: np.ndarray  # (8, 2): ((x - cx) / w, (y - cy) / h)
    counts: np.ndarray  # (8,) objects that had the corner in front of the camera

    def to_dict(self) -> dict[str, Any]:
        return {"corners": self.corners.tolist(), "counts": self.counts.tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Layout":
        return cls(np.asarray(d["corners"], dtype=np.float64).reshape(NUM_KEYPOINTS, 2),
                   np.asarray(d["counts"], dtype=np.int64).reshape(NUM_KEYPOINTS))


@dataclass
class BoxTemplate:
    """Mean layouts per (class, view), per class and overall; `layout` picks per corner."""

    taxonomy: str
    classes: list[str]  # the taxonomy's classes: a prediction's category_id - 1 indexes them
    fitted_from: str  # 'train' or 'all frames'
    frames: int  # frames it was fitted on
    min_objects: int
    overall: Layout
    by_class: dict[str, Layout] = field(default_factory=dict)
    by_class_view: dict[str, dict[str, Layout]] = field(default_factory=dict)  # class -> view -> layout

    def layout(self, class_name: str, view: str) -> np.ndarray:
        """(8, 2): each corner from the most specific level with at least min_objects objects."""
        out = np.where(self.overall.counts[:, None] > 0, self.overall.corners, 0.0)
        for level in (self.by_class.get(class_name), self.by_class_view.get(class_name, {}).get(view)):
            if level is not None:
                out = np.where(level.counts[:, None] >= self.min_objects, level.corners, out)
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"taxonomy": self.taxonomy, "classes": list(self.classes), "fitted_from": self.fitted_from,
                "frames": self.frames, "min_objects": self.min_objects, "overall": self.overall.to_dict(),
                "by_class": {c: v.to_dict() for c, v in self.by_class.items()},
                "by_class_view": {c: {w: v.to_dict() for w, v in views.items()}
                                  for c, views in self.by_class_view.items()}}

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "BoxTemplate":
        return cls(taxonomy=d["taxonomy"], classes=list(d["classes"]), fitted_from=d["fitted_from"],
                   frames=int(d["frames"]), min_objects=int(d["min_objects"]), overall=Layout.from_dict(d["overall"]),
                   by_class={c: Layout.from_dict(v) for c, v in d["by_class"].items()},
                   by_class_view={c: {w: Layout.from_dict(v) for w, v in views.items()}
                                  for c, views in d["by_class_view"].items()})


def frame_views(ds: Dataset) -> tuple[np.ndarray, np.ndarray]:
    """The dataset's view names (sorted) and each frame's index into them: the key of a layout."""
    names, of_frame = np.unique(np.asarray(ds.table.view, dtype=object), return_inverse=True)
    return names, of_frame.reshape(-1)


def training_frames(ds: Dataset) -> tuple[list[str], str]:
    """The frames a template (or any prior) is fitted on: the 'train' split, else all frames."""
    if TRAIN in split_names(ds.root):
        return read_split(ds.root, TRAIN), TRAIN
    return list(ds.table.frame_id), "all frames"


def _means(keys: np.ndarray, n_keys: int, norm: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per key: (n_keys, 8, 2) mean of the valid corners (0 where none) and (n_keys, 8) counts."""
    sums = np.zeros((n_keys, NUM_KEYPOINTS, 2))
    counts = np.zeros((n_keys, NUM_KEYPOINTS), dtype=np.int64)
    np.add.at(sums, keys, np.where(valid[:, :, None], norm, 0.0))
    np.add.at(counts, keys, valid.astype(np.int64))
    return np.where(counts[:, :, None] > 0, sums / np.maximum(counts, 1)[:, :, None], 0.0), counts


def fit_box_template(ds: Dataset, frames: str | Sequence[str] | None, taxonomy: Taxonomy | str = "fine",
                     min_objects: int = MIN_OBJECTS, fitted_from: str | None = None) -> BoxTemplate:
    """Learn the mean normalized corner layouts from the objects of `frames`.

    `frames`: a split name, a list of frame ids, or None for every frame. Use the training split
    (training_frames(ds)); `fitted_from` labels it in the template (default: the split's name,
    'frame list' or 'all frames').
    """
    taxonomy = load_taxonomy(taxonomy) if isinstance(taxonomy, str) else taxonomy
    if isinstance(frames, str):
        fitted_from = fitted_from or frames
        frames = read_split(ds.root, frames)
    elif frames is None:
        fitted_from = fitted_from or "all frames"
        frames = list(ds.table.frame_id)
    else:
        fitted_from = fitted_from or "frame list"
    index = np.asarray([ds.index_of(str(f)) for f in frames], dtype=np.int64)
    t = ds.objects
    in_frames = np.zeros(len(ds), bool)
    in_frames[index] = True
    cls = taxonomy.fine_class_ids()[t.category] if len(t) else np.zeros(0, np.int64)
    box = t.bbox
    wh = box[:, 2:] - box[:, :2]
    keep = in_frames[t.frame] & (cls >= 0) & (wh > 0).all(axis=1)
    if not keep.any():
        raise ValueError(f"{ds.root}: no object with a 2D box in the {len(index)} frames to fit the box template on")
    kp, box, wh, cls = t.keypoints[keep], box[keep], wh[keep], cls[keep]
    valid = ~t.behind_camera[keep].astype(bool) & np.isfinite(kp).all(axis=2)
    norm = (np.nan_to_num(kp) - (box[:, None, :2] + box[:, None, 2:]) / 2) / wh[:, None, :]
    view_names, view_of_frame = frame_views(ds)
    views = view_of_frame[t.frame[keep]]
    n_cls, n_views = len(taxonomy.classes), len(view_names)
    overall, overall_n = _means(np.zeros(len(cls), np.int64), 1, norm, valid)
    per_cls, per_cls_n = _means(cls, n_cls, norm, valid)
    per_pair, per_pair_n = _means(cls * n_views + views, n_cls * n_views, norm, valid)
    by_class, by_pair = {}, {}
    for c, name in enumerate(taxonomy.classes):
        if per_cls_n[c].any():
            by_class[name] = Layout(per_cls[c], per_cls_n[c])
        pairs = {str(view_names[v]): Layout(per_pair[c * n_views + v], per_pair_n[c * n_views + v])
                 for v in range(n_views) if per_pair_n[c * n_views + v].any()}
        if pairs:
            by_pair[name] = pairs
    return BoxTemplate(taxonomy=taxonomy.name, classes=list(taxonomy.classes), fitted_from=fitted_from,
                       frames=len(index), min_objects=min_objects, overall=Layout(overall[0], overall_n[0]),
                       by_class=by_class, by_class_view=by_pair)


def _frame_index(p: dict[str, Any], ds: Dataset, where: str) -> int:
    if p.get("frame_id") is not None:
        try:
            return ds.index_of(str(p["frame_id"]))
        except KeyError:
            raise PredictionError(f"{where}: field 'frame_id': no frame {p['frame_id']!r} in {ds.root}") from None
    image_id = p.get("image_id")
    if not isinstance(image_id, int) or isinstance(image_id, bool) or not 1 <= image_id <= len(ds):
        raise PredictionError(f"{where}: field 'image_id': unknown image id {image_id!r} (ids are 1..{len(ds)})")
    return image_id - 1


def apply(template: BoxTemplate, predictions: Sequence[dict[str, Any]], ds: Dataset,
          source: str = "<predictions>") -> list[dict[str, Any]]:
    """The predictions with their corners replaced by the template placed into their boxes.

    Same boxes, scores, classes and frame ids (copies; the input is not changed); every corner
    gets v = BASELINE_VISIBILITY. Each prediction needs its bbox (x, y, w, h): the baseline has
    nothing else to go on.
    """
    n = len(predictions)
    frames = np.zeros(n, np.int64)
    cats = np.zeros(n, np.int64)
    boxes = np.zeros((n, 4))
    for i, p in enumerate(predictions):
        where = f"{source}: prediction {i}"
        frames[i] = _frame_index(p, ds, where)
        cat = p.get("category_id")
        if not isinstance(cat, int) or isinstance(cat, bool) or not 1 <= cat <= len(template.classes):
            raise PredictionError(f"{where}: field 'category_id': {cat!r} is not a category id "
                                  f"1..{len(template.classes)} of the template's taxonomy {template.taxonomy!r}")
        cats[i] = cat - 1
        b = p.get("bbox")
        if not isinstance(b, list) or len(b) != 4 or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in b):
            raise PredictionError(f"{where}: field 'bbox': the box template baseline needs each prediction's "
                                  f"2D box (x, y, w, h, four finite numbers)")
        boxes[i] = b
    view_names, view_of_frame = frame_views(ds)
    table = np.asarray([[template.layout(c, str(v)) for v in view_names] for c in template.classes])
    layout = table[cats, view_of_frame[frames]] if n else np.zeros((0, NUM_KEYPOINTS, 2))
    xy = boxes[:, None, :2] + boxes[:, None, 2:] / 2 + layout * boxes[:, None, 2:]
    kp = np.concatenate([xy, np.full((n, NUM_KEYPOINTS, 1), BASELINE_VISIBILITY)], axis=2).reshape(n, 3 * NUM_KEYPOINTS).tolist()
    return [{**p, "keypoints": k} for p, k in zip(predictions, kp)]


def evaluate_with_baseline(ds: Dataset, predictions: Sequence[dict[str, Any]], split: str | None = None,
                           taxonomy: Taxonomy | str = "fine", template: BoxTemplate | None = None,
                           **options: Any) -> tuple[EvalReport, EvalReport]:
    """The model's report and the box-template baseline's, by the same evaluate(..., **options).

    `template`: None fits one on training_frames(ds) (the 'train' split, else all frames) with the
    same taxonomy. The baseline report's notes say where its template came from, and warn when that
    includes the evaluated frames.
    """
    taxonomy = load_taxonomy(taxonomy) if isinstance(taxonomy, str) else taxonomy
    source = options.get("source", "<predictions>")
    report = evaluate(ds, predictions, split=split, taxonomy=taxonomy, **options)  # checks the predictions first
    if template is None:
        frames, fitted_from = training_frames(ds)
        template = fit_box_template(ds, frames, taxonomy, fitted_from=fitted_from)
    if template.classes != list(taxonomy.classes):
        raise ValueError(f"box template of taxonomy {template.taxonomy!r} does not match the predictions' "
                         f"taxonomy {taxonomy.name!r}")
    baseline = evaluate(ds, apply(template, predictions, ds, source), split=split, taxonomy=taxonomy, **options)
    baseline.notes.insert(0, f"box-template baseline: mean corner layouts per (class, view) of "
                             f"{template.frames} frames ({template.fitted_from})")
    if template.fitted_from in ("all frames", split) or split is None:
        baseline.notes.insert(1, "the box template was fitted on frames that include the evaluated ones")
    return report, baseline
