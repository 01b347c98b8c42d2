"""`omnigen eval-kitti`: KITTI AP by the official devkit's definition (issue 11, item 3).

Hand-computed cases pin each rule (recall sampling from the valid count, DontCare, neighbour
classes, overlap exactly at the threshold, difficulty filters, rotated overlaps); a slow reference
written as the devkit's plain loops checks the vectorized evaluator on randomized frames; real KITTI
labels come from ../shared/realdata/kitti (skipped with a reason when absent).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import pytest
import shapely
from shapely.geometry import Polygon

from omnigen.detector.evaluation import kitti_eval as ke
from omnigen.detector import kitti_eval_command

REAL_LABELS = Path(__file__).resolve().parents[2].parent / "shared" / "realdata" / "kitti" / "training" / "label_2"


# ---------------------------------------------------------------------------------------------
# building frames
# ---------------------------------------------------------------------------------------------


def obj(name="Car", box=(100, 100, 200, 200), trunc=0.0, occ=0, loc=(0.0, 1.5, 20.0), dims=(1.5, 1.6, 4.0),
        ry=0.0, score=None) -> tuple[str, list[float]]:
    row = [trunc, occ, -10.0, *box, *dims, *loc, ry]
    if score is not None:
        row.append(score)
    return name, row


def frame(*objs) -> ke.KittiLabels:
    return ke.labels_from_rows([o[0] for o in objs], [o[1] for o in objs])


def car_row(i: int, **kw):
    """The i-th of a set of well-separated, easy cars (2D and 3D boxes far apart)."""
    x = 150.0 * i
    return obj(box=(x, 100, x + 100, 200), loc=(10.0 * i, 1.5, 20.0), **kw)


def ap(result, kind, cls, metric):
    return result[kind][cls][metric]


# ---------------------------------------------------------------------------------------------
# a slow reference: the devkit's loops, one frame and one detection at a time
# ---------------------------------------------------------------------------------------------


def ref_overlap(metric, d: ke.KittiLabels, j, g: ke.KittiLabels, i, criterion=-1):
    if metric == "bbox":
        a, b = d.bbox[j], g.bbox[i]
        w = min(a[2], b[2]) - max(a[0], b[0])
        h = min(a[3], b[3]) - max(a[1], b[1])
        if w <= 0 or h <= 0:
            return 0.0
        inter = w * h
        area_a = (a[2] - a[0]) * (a[3] - a[1])
        area_b = (b[2] - b[0]) * (b[3] - b[1])
        return inter / area_a if criterion == 0 else inter / (area_a + area_b - inter)

    def poly(lab, k):
        c, s = math.cos(lab.rotation_y[k]), math.sin(lab.rotation_y[k])
        h, w, l = lab.dims[k]
        x, _, z = lab.location[k]
        pts = [(l / 2, w / 2), (l / 2, -w / 2), (-l / 2, -w / 2), (-l / 2, w / 2)]
        return Polygon([(x + c * u + s * v, z - s * u + c * v) for u, v in pts])

    pd, pg = poly(d, j), poly(g, i)
    inter = pd.intersection(pg).area
    if metric == "bev":
        union = pd.area + pg.area - inter
        return inter / union if union > 0 else 0.0
    yd, yg = d.location[j][1], g.location[i][1]
    hd, hg = d.dims[j][0], g.dims[i][0]
    inter *= max(0.0, min(yd, yg) - max(yd - hd, yg - hg))
    union = np.prod(d.dims[j]) + np.prod(g.dims[i]) - inter
    return inter / union if union > 0 else 0.0


def ref_clean(g: ke.KittiLabels, d: ke.KittiLabels, cls, level):
    name = cls.lower()
    ig_gt, dc, n_valid = [], [], 0
    for i in range(len(g)):
        gname = g.names[i].lower()
        valid = 1 if gname == name else 0 if (name, gname) in (("car", "van"), ("pedestrian", "person_sitting")) else -1
        height = g.bbox[i][3] - g.bbox[i][1]
        ignore = (g.occluded[i] > ke.MAX_OCCLUSION[level] or g.truncated[i] > ke.MAX_TRUNCATION[level]
                  or height < ke.MIN_HEIGHT[level])
        if valid == 1 and not ignore:
            ig_gt.append(0)
            n_valid += 1
        elif valid == 0 or (ignore and valid == 1):
            ig_gt.append(1)
        else:
            ig_gt.append(-1)
        if gname == "dontcare":
            dc.append(i)
    ig_det = []
    for j in range(len(d)):
        height = int(abs(d.bbox[j][1] - d.bbox[j][3]))  # the devkit truncates to int here
        ig_det.append(1 if height < ke.MIN_HEIGHT[level] else 0 if d.names[j].lower() == name else -1)
    return ig_gt, ig_det, dc, n_valid


def ref_statistics(g, d, ig_gt, ig_det, dc, metric, mo, compute_fp, thresh=0.0):
    assigned = [False] * len(d)
    ignored_thr = [compute_fp and d.score[j] < thresh for j in range(len(d))]
    tp = fp = fn = 0
    scores = []
    for i in range(len(g)):
        if ig_gt[i] == -1:
            continue
        det_idx, valid, max_ov, assigned_ignored = -1, ke.NO_DETECTION, 0.0, False
        for j in range(len(d)):
            if ig_det[j] == -1 or assigned[j] or ignored_thr[j]:
                continue
            ov = ref_overlap(metric, d, j, g, i)
            if not compute_fp and ov > mo and d.score[j] > valid:
                det_idx, valid = j, d.score[j]
            elif compute_fp and ov > mo and (ov > max_ov or assigned_ignored) and ig_det[j] == 0:
                max_ov, det_idx, valid, assigned_ignored = ov, j, 1, False
            elif compute_fp and ov > mo and valid == ke.NO_DETECTION and ig_det[j] == 1:
                det_idx, valid, assigned_ignored = j, 1, True
        if valid == ke.NO_DETECTION and ig_gt[i] == 0:
            fn += 1
        elif valid != ke.NO_DETECTION and (ig_gt[i] == 1 or ig_det[det_idx] == 1):
            assigned[det_idx] = True
        elif valid != ke.NO_DETECTION:
            tp += 1
            scores.append(d.score[det_idx])
            assigned[det_idx] = True
    if compute_fp:
        fp = sum(1 for j in range(len(d)) if not (assigned[j] or ig_det[j] != 0 or ignored_thr[j]))
        nstuff = 0
        for i in dc:
            for j in range(len(d)):
                if assigned[j] or ig_det[j] != 0 or ignored_thr[j]:
                    continue
                # the DontCare label's 3D box is a -1000 placeholder: only the 2D test can ever fire
                if metric == "bbox" and ref_overlap("bbox", d, j, g, i, criterion=0) > mo:
                    assigned[j] = True
                    nstuff += 1
        fp -= nstuff
    return tp, fp, fn, scores


def ref_thresholds(scores, n_gt):
    v = sorted(scores, reverse=True)
    out, current = [], 0.0
    for i in range(len(v)):
        l_recall = (i + 1) / n_gt
        r_recall = (i + 2) / n_gt if i < len(v) - 1 else l_recall
        if (r_recall - current) < (current - l_recall) and i < len(v) - 1:
            continue
        out.append(v[i])
        current += 1.0 / 40.0
    return out


def reference(gts, preds, classes=ke.CLASSES):
    result = {"AP40": {}, "AP11": {}}
    for cls in classes:
        result["AP40"][cls], result["AP11"][cls] = {}, {}
        for metric in ke.METRICS:
            a40, a11 = [], []
            for level in range(3):
                clean = [ref_clean(g, d, cls, level) for g, d in zip(gts, preds)]
                n_valid = sum(c[3] for c in clean)
                scores = []
                for (g, d), (ig_gt, ig_det, dc, _) in zip(zip(gts, preds), clean):
                    scores += ref_statistics(g, d, ig_gt, ig_det, dc, metric, ke.MIN_OVERLAP[cls], False)[3]
                thresholds = ref_thresholds(scores, n_valid) if n_valid else []
                precision = [0.0] * 41
                for t_i, t in enumerate(thresholds):
                    tp = fp = 0
                    for (g, d), (ig_gt, ig_det, dc, _) in zip(zip(gts, preds), clean):
                        s = ref_statistics(g, d, ig_gt, ig_det, dc, metric, ke.MIN_OVERLAP[cls], True, t)
                        tp, fp = tp + s[0], fp + s[1]
                    precision[t_i] = tp / (tp + fp) if tp + fp else 0.0
                precision = [max(precision[k:]) for k in range(41)]
                a40.append(sum(precision[1:]) / 40 * 100)
                a11.append(sum(precision[0::4]) / 11 * 100)
            result["AP40"][cls][metric], result["AP11"][cls][metric] = a40, a11
    return result


def random_frames(rng: np.random.Generator, n_frames: int):
    """Crowded frames (overlapping objects, Van, Person_sitting, DontCare, low boxes, duplicates)."""
    names = ["Car", "Car", "Van", "Pedestrian", "Person_sitting", "Cyclist", "Truck", "DontCare"]
    gts, preds = [], []
    for _ in range(n_frames):
        g_objs, d_objs = [], []
        for _ in range(rng.integers(0, 7)):
            name = names[rng.integers(len(names))]
            x1, y1 = rng.uniform(0, 300), rng.uniform(0, 100)
            box = (x1, y1, x1 + rng.uniform(10, 90), y1 + rng.uniform(15, 70))
            loc = (rng.uniform(-4, 4), rng.uniform(1.0, 2.0), rng.uniform(8, 16))
            dims = (rng.uniform(1.2, 1.8), rng.uniform(0.5, 2.0), rng.uniform(0.5, 4.5))
            ry = rng.uniform(-math.pi, math.pi)
            g_objs.append(obj(name, box, float(rng.choice([0.0, 0.2, 0.4, 0.6])), int(rng.integers(0, 4)),
                              loc, dims, ry))
            for _ in range(rng.integers(0, 3)):  # 0 to 2 detections per object (duplicates)
                jit = rng.normal(0, 4, 4)
                dname = name if rng.random() < 0.8 else ["Car", "Pedestrian", "Cyclist"][rng.integers(3)]
                if dname not in ke.CLASSES:
                    dname = "Car"
                d_objs.append(obj(dname, tuple(np.array(box) + jit), 0.0, 0,
                                  tuple(np.array(loc) + rng.normal(0, 0.3, 3)),
                                  tuple(np.array(dims) * rng.uniform(0.85, 1.15, 3)),
                                  ry + rng.normal(0, 0.2), float(np.round(rng.random(), 2))))
        for _ in range(rng.integers(0, 2)):  # false alarms
            x1 = rng.uniform(0, 300)
            name = ["Car", "Pedestrian", "Cyclist"][rng.integers(3)]
            loc = (rng.uniform(-4, 4), 1.5, rng.uniform(8, 16))
            d_objs.append(obj(name, (x1, 50, x1 + 50, 50 + rng.uniform(15, 80)), 0.0, 0, loc, (1.5, 1.6, 3.9), 0.0,
                              float(np.round(rng.random(), 2))))
        gts.append(frame(*g_objs))
        preds.append(frame(*d_objs))
    return gts, preds


def test_matches_the_slow_reference_on_randomized_frames():
    rng = np.random.default_rng(11)
    gts, preds = random_frames(rng, 100)
    got, want = ke.evaluate(gts, preds), reference(gts, preds)
    for kind in ("AP40", "AP11"):
        for cls in ke.CLASSES:
            for metric in ke.METRICS:
                assert got[kind][cls][metric] == pytest.approx(want[kind][cls][metric], abs=1e-9), (kind, cls, metric)
    # the case is not degenerate: some values are neither 0 nor 100
    values = [v for k in got.values() for c in k.values() for m in c.values() for v in m]
    assert any(0 < v < 100 for v in values)


# ---------------------------------------------------------------------------------------------
# hand-computed cases
# ---------------------------------------------------------------------------------------------


def test_perfect_predictions_score_100_everywhere():
    """45 valid objects a class (more than 41): every AP is 100."""
    gts, preds = [], []
    for f in range(15):
        objs = []
        for i, name in enumerate(("Car", "Pedestrian", "Cyclist")):
            for k in range(3):
                objs.append(car_row(3 * i + k)[1])
        names = [n for n in ("Car", "Pedestrian", "Cyclist") for _ in range(3)]
        gts.append(ke.labels_from_rows(names, objs))
        preds.append(ke.labels_from_rows(names, [r + [0.9] for r in objs]))
    result = ke.evaluate(gts, preds)
    for kind in ("AP40", "AP11"):
        for cls in ke.CLASSES:
            for metric in ke.METRICS:
                assert result[kind][cls][metric] == pytest.approx([100.0] * 3), (kind, cls, metric)


def test_recall_sampling_uses_the_valid_count_and_caps_ap():
    """5 valid cars, all found: only 5 thresholds exist, stored at recall positions 0..4.

    AP40 = 4 / 40 = 10 %, AP11 = positions 0 and 4 = 2 / 11 = 18.18 %: the official numbers (the
    C++ devkit and the Python port agree), not 100. An ignored car (too low for Easy) does not
    enter the denominator, so Moderate has 6 objects: AP40 = 5 / 40.
    """
    gt = frame(*[car_row(i) for i in range(5)], obj(box=(900, 100, 1000, 130), loc=(60.0, 1.5, 20.0)))
    pred = frame(*[car_row(i, score=0.5 + 0.1 * i) for i in range(5)],
                 obj(box=(900, 100, 1000, 130), loc=(60.0, 1.5, 20.0), score=0.3))
    r = ke.evaluate([gt], [pred], classes=("Car",))
    assert ap(r, "AP40", "Car", "bbox") == pytest.approx([10.0, 12.5, 12.5])
    assert ap(r, "AP11", "Car", "bbox") == pytest.approx([200 / 11, 200 / 11, 200 / 11])
    assert ke.get_thresholds(np.array([0.5, 0.9, 0.7]), 3).tolist() == [0.9, 0.7, 0.5]


def test_get_thresholds_samples_41_positions_from_many_objects():
    scores = np.linspace(1.0, 0.0, 400, endpoint=False)
    t = ke.get_thresholds(scores, 400)
    assert len(t) == 41
    assert t[0] == scores[0] and t[-1] == scores[-1]
    # each kept score reaches the next recall position i / 40 (10 objects a step)
    assert t[1] == pytest.approx(scores[9])


def _found_cars(n_gt: int, n_found: int, fp_score: float | None):
    """n_gt easy cars over frames of 8; the first n_found detected (scores falling), one FP scored fp_score."""
    gt_rows = [car_row(i % 8)[1] for i in range(n_gt)]
    gts, preds = [], []
    for f in range(0, n_gt, 8):
        gts.append(ke.labels_from_rows(["Car"] * len(gt_rows[f:f + 8]), gt_rows[f:f + 8]))
        rows = [gt_rows[k] + [0.9 - 0.001 * k] for k in range(f, min(f + 8, n_found))]
        names = ["Car"] * len(rows)
        if f == 0 and fp_score is not None:
            names.append("Car")
            rows.append(obj(box=(5000, 100, 5100, 200), loc=(-30.0, 1.5, 60.0), score=fp_score)[1])
        preds.append(ke.labels_from_rows(names, rows))
    return gts, preds


@pytest.mark.parametrize("n_gt, n_found, want40, want11", [
    # 80 objects, all found, a FP above them: precision rises with recall, so after "max to the
    # right" all 41 points hold 80/81
    (80, 80, 100 * 80 / 81, 100 * 80 / 81),
    # 80 objects, the best 40 found: thresholds at tp = 1, 2, 4, ..., 40 (21 of them, the recall
    # positions 0..20/40), each 40/41 after the max: AP40 = 20/40 * 40/41, AP11 = 6/11 * 40/41
    (80, 40, 100 * 20 / 40 * 40 / 41, 100 * 6 / 11 * 40 / 41),
    # 4 objects, all found: 4 thresholds only (the cap), precision 4/5: AP40 = 3 * 0.8 / 40, AP11 = 0.8 / 11
    (4, 4, 6.0, 100 * 0.8 / 11),
])
def test_one_false_positive_above_all_true_positives(n_gt, n_found, want40, want11):
    gts, preds = _found_cars(n_gt, n_found, fp_score=0.99)
    r = ke.evaluate(gts, preds, classes=("Car",))
    for metric in ke.METRICS:
        assert ap(r, "AP40", "Car", metric) == pytest.approx([want40] * 3), metric
        assert ap(r, "AP11", "Car", metric) == pytest.approx([want11] * 3), metric
    # without the FP the same detections score 100 % precision at the same points
    clean = ke.evaluate(*_found_cars(n_gt, n_found, fp_score=None), classes=("Car",))
    assert ap(clean, "AP40", "Car", "bbox")[0] == pytest.approx(want40 * (n_found + 1) / n_found)


def test_get_thresholds_keeps_the_scores_nearest_each_recall_position():
    t = ke.get_thresholds(np.arange(80, 0, -1) / 100, 80)  # 80 TPs of 80 objects: tp 1, 2, 4, ..., 80
    assert len(t) == 41
    assert t[:4].tolist() == [0.80, 0.79, 0.77, 0.75]


def _many_cars(extra_gt=(), extra_pred=()):
    """45 found cars over 5 frames (AP 100 alone), plus extra objects in the first frame."""
    gts, preds = [], []
    for f in range(5):
        rows = [car_row(i) for i in range(9)]
        g = rows + (list(extra_gt) if f == 0 else [])
        d = [car_row(i, score=0.8) for i in range(9)] + (list(extra_pred) if f == 0 else [])
        gts.append(frame(*g))
        preds.append(frame(*d))
    return gts, preds


def test_a_detection_in_a_dontcare_region_is_not_a_false_positive():
    fp = obj(box=(2000, 100, 2100, 200), loc=(-40.0, 1.5, 30.0), score=0.95)
    gts, preds = _many_cars(extra_pred=[fp])
    with_fp = ke.evaluate(gts, preds, classes=("Car",))
    assert ap(with_fp, "AP40", "Car", "bbox")[0] < 100
    # a DontCare region holding 80 % of the detection's area (> 0.7): not counted
    dc = obj("DontCare", (2020, 100, 2120, 200), -1, -1, (-1000, -1000, -1000), (-1, -1, -1), -10)
    gts_dc, _ = _many_cars(extra_gt=[dc])
    r = ke.evaluate(gts_dc, preds, classes=("Car",))
    assert ap(r, "AP40", "Car", "bbox") == pytest.approx([100.0] * 3)
    # the DontCare label has no 3D box: in BEV and 3D the detection stays a FP (as in the devkit)
    assert ap(r, "AP40", "Car", "bev") == ap(with_fp, "AP40", "Car", "bev")
    # 70 % exactly is not more than 0.7: a FP again
    dc70 = obj("DontCare", (2030, 100, 2130, 200), -1, -1, (-1000, -1000, -1000), (-1, -1, -1), -10)
    r70 = ke.evaluate(_many_cars(extra_gt=[dc70])[0], preds, classes=("Car",))
    assert ap(r70, "AP40", "Car", "bbox") == ap(with_fp, "AP40", "Car", "bbox")


def test_dontcare_also_covers_an_unmatched_duplicate():
    """A second detection of a found car is a FP, unless a DontCare region holds it."""
    dup = dict(box=(2000, 100, 2100, 200), loc=(-40.0, 1.5, 30.0))
    gts, preds = _many_cars(extra_gt=[obj("Car", **dup)], extra_pred=[obj("Car", **dup, score=0.95),
                                                                       obj("Car", **dup, score=0.97)])
    assert ap(ke.evaluate(gts, preds, classes=("Car",)), "AP40", "Car", "bbox")[0] < 100
    dc = obj("DontCare", dup["box"], -1, -1, (-1000, -1000, -1000), (-1, -1, -1), -10)
    gts_dc, _ = _many_cars(extra_gt=[obj("Car", **dup), dc])
    assert ap(ke.evaluate(gts_dc, preds, classes=("Car",)), "AP40", "Car", "bbox") == pytest.approx([100.0] * 3)


def test_a_low_detection_of_any_class_takes_part_in_matching():
    """The devkit marks every detection under the minimum height as ignored before it looks at the
    class, so it competes for objects. A 40 px car, a 39.5 px pedestrian detection on it scored 0.9
    and a car detection on it scored 0.5: when collecting thresholds the car takes the highest score,
    the ignored pedestrian detection, so Easy has no TP score at all (AP 0). For Moderate, 39.5 px is
    not low: the pedestrian detection is not evaluated and the car detection gives AP11 = 1/11."""
    gt = frame(obj("Car", box=(0, 100, 100, 140)))
    pred = frame(obj("Pedestrian", box=(0, 100, 100, 139.5), score=0.9),
                 obj("Car", box=(0, 100, 100, 145), score=0.5))
    r = ke.evaluate([gt], [pred], classes=("Car",))
    assert ap(r, "AP11", "Car", "bbox") == pytest.approx([0.0, 100 / 11, 100 / 11])
    without = ke.evaluate([gt], [frame(obj("Car", box=(0, 100, 100, 145), score=0.5))], classes=("Car",))
    assert ap(without, "AP11", "Car", "bbox") == pytest.approx([100 / 11] * 3)


def test_precision_points_match_by_greatest_overlap_thresholds_by_highest_score():
    """Two cars 30 px apart; D1 between them (IoU 0.739 with both) comes first in the file, D2 sits on
    the first car (IoU 1, 0.538 with the second). Matching by greatest overlap gives both cars a
    detection at threshold 0.8; taking the first candidate would give one TP and one FP.
    Two valid cars, both found: thresholds 0.9 and 0.8, precision 1 at positions 0 and 1:
    AP40 = 1/40, AP11 = 1/11."""
    gt = frame(obj(box=(0, 100, 100, 200), loc=(0.0, 1.5, 20.0)), obj(box=(30, 100, 130, 200), loc=(9.0, 1.5, 20.0)))
    pred = frame(obj(box=(15, 100, 115, 200), loc=(9.0, 1.5, 20.0), score=0.8),
                 obj(box=(0, 100, 100, 200), loc=(0.0, 1.5, 20.0), score=0.9))
    r = ke.evaluate([gt], [pred], classes=("Car",))
    assert ap(r, "AP40", "Car", "bbox") == pytest.approx([2.5] * 3)
    assert ap(r, "AP11", "Car", "bbox") == pytest.approx([100 / 11] * 3)


def test_a_detected_van_is_not_a_false_positive_for_car():
    van_box = dict(box=(2000, 100, 2100, 200), loc=(-40.0, 1.5, 30.0))
    van_gt = obj("Van", **van_box)
    car_on_van = obj("Car", **van_box, score=0.95)
    gts, preds = _many_cars(extra_gt=[van_gt], extra_pred=[car_on_van])
    r = ke.evaluate(gts, preds, classes=("Car",))
    for metric in ke.METRICS:
        assert ap(r, "AP40", "Car", metric) == pytest.approx([100.0] * 3)
    # the same detection on a Truck is a FP (Truck is no neighbour of Car)
    gts_t, preds_t = _many_cars(extra_gt=[obj("Truck", **van_box)], extra_pred=[car_on_van])
    assert ap(ke.evaluate(gts_t, preds_t, classes=("Car",)), "AP40", "Car", "bbox")[0] < 100
    # and an undetected Van is no FN
    gts_m, preds_m = _many_cars(extra_gt=[van_gt])
    assert ap(ke.evaluate(gts_m, preds_m, classes=("Car",)), "AP40", "Car", "bbox") == pytest.approx([100.0] * 3)


def test_overlap_exactly_at_the_threshold_does_not_match():
    """The devkit matches on overlap > min_overlap: IoU 0.7 exactly is a miss for Car, 0.5 for Pedestrian."""
    # 2D: gt 100x70 inside det 100x100: IoU = 7000 / 10000 = 0.7 exactly in floating point
    assert ke.box2d_iou(np.array([[0.0, 0, 100, 100]]), np.array([[0.0, 0, 100, 70]]))[0] == 0.7
    gt = frame(obj(box=(0, 100, 100, 170)))
    at = frame(obj(box=(0, 100, 100, 200), score=0.9))
    above = frame(obj(box=(0, 100, 100, 199), score=0.9))
    assert ap(ke.evaluate([gt], [at], ("Car",)), "AP11", "Car", "bbox")[0] == 0.0
    assert ap(ke.evaluate([gt], [above], ("Car",)), "AP11", "Car", "bbox")[0] == pytest.approx(100 / 11)
    # BEV and 3D: a 4 x 2 footprint against one shifted by 4/3 m in x: IoU = (8/3) / (16 - 8/3) ... use 0.5:
    # pedestrians 1 x 1, shifted by 1/3 m: inter 2/3, union 4/3 -> 0.5 exactly
    ped = dict(box=(0, 100, 40, 180), dims=(1.7, 1.0, 1.0))
    g = frame(obj("Pedestrian", loc=(0.0, 1.5, 10.0), **ped))
    d = frame(obj("Pedestrian", loc=(1.0 / 3.0, 1.5, 10.0), score=0.9, **ped))
    d_in = frame(obj("Pedestrian", loc=(0.33, 1.5, 10.0), score=0.9, **ped))
    ov = ke.rotated_overlaps(d, g, np.array([0]), np.array([0]), volume=False)[0]
    assert ov == pytest.approx(0.5, abs=1e-15)
    r_at = ke.evaluate([g], [d], ("Pedestrian",))
    r_in = ke.evaluate([g], [d_in], ("Pedestrian",))
    if ov == 0.5:  # exact in floating point: must not match
        assert ap(r_at, "AP11", "Pedestrian", "bev")[0] == 0.0
    assert ap(r_in, "AP11", "Pedestrian", "bev")[0] == pytest.approx(100 / 11)
    assert ap(r_in, "AP11", "Pedestrian", "3d")[0] == pytest.approx(100 / 11)


def test_identical_rotated_boxes_have_iou_one():
    rng = np.random.default_rng(3)
    n = 200
    lab = frame(*[obj(loc=tuple(rng.uniform(-20, 20, 3)), dims=tuple(rng.uniform(0.3, 5, 3)),
                      ry=float(rng.uniform(-math.pi, math.pi))) for _ in range(n)])
    idx = np.arange(n)
    assert ke.rotated_overlaps(lab, lab, idx, idx, volume=False) == pytest.approx(np.ones(n), abs=1e-12)
    assert ke.rotated_overlaps(lab, lab, idx, idx, volume=True) == pytest.approx(np.ones(n), abs=1e-12)


def test_rotated_bev_iou_of_known_rectangles():
    # a 4 x 2 car and the same car turned 90 degrees about the same centre: the overlap is a 2 x 2 square
    a = frame(obj(loc=(1.0, 1.5, 5.0), dims=(1.5, 2.0, 4.0), ry=0.0))
    b = frame(obj(loc=(1.0, 1.5, 5.0), dims=(1.5, 2.0, 4.0), ry=math.pi / 2))
    zero = np.array([0])
    assert ke.rotated_overlaps(a, b, zero, zero, volume=False)[0] == pytest.approx(4 / 12)
    # turned 45 degrees: compare with shapely's own rotation of the rectangle
    c = frame(obj(loc=(1.5, 1.2, 5.5), dims=(1.0, 2.0, 4.0), ry=math.pi / 4))
    rect = Polygon([(-2, -1), (2, -1), (2, 1), (-2, 1)])
    pa = shapely.affinity.translate(rect, 1.0, 5.0)
    # ry turns the length axis from +x towards -z: a rotation by -ry in the x-z plane
    pc = shapely.affinity.translate(shapely.affinity.rotate(rect, -45, origin=(0, 0)), 1.5, 5.5)
    inter = pa.intersection(pc).area
    assert ke.rotated_overlaps(c, a, zero, zero, volume=False)[0] == pytest.approx(inter / (16 - inter))
    # 3D: vertical overlap [0.2, 1.2] of heights 1.5 ([0, 1.5]) and 1.0 ([0.2, 1.2]) is 1.0
    vol = inter * 1.0
    assert ke.rotated_overlaps(c, a, zero, zero, volume=True)[0] == pytest.approx(vol / (8 + 12 - vol))
    # the corners follow the devkit: the length axis of ry = pi/2 points along -z
    corners = ke.bev_corners(np.array([[0.0, 0, 0]]), np.array([[1.0, 2.0, 4.0]]), np.array([math.pi / 2]))[0]
    assert corners[0] == pytest.approx([1.0, -2.0])


def test_difficulty_filters():
    """A 30 px tall car counts for Moderate and Hard, not Easy; occlusion and truncation likewise."""
    small = frame(obj(box=(0, 100, 80, 130)))
    found = frame(obj(box=(0, 100, 80, 130), score=0.9))
    r = ke.evaluate([small], [found], ("Car",))
    assert ap(r, "AP11", "Car", "bbox") == pytest.approx([0.0, 100 / 11, 100 / 11])
    occluded = frame(obj(box=(0, 100, 80, 200), occ=1))
    r = ke.evaluate([occluded], [frame(obj(box=(0, 100, 80, 200), score=0.9))], ("Car",))
    assert ap(r, "AP11", "Car", "bbox") == pytest.approx([0.0, 100 / 11, 100 / 11])
    truncated = frame(obj(box=(0, 100, 80, 200), trunc=0.4))
    r = ke.evaluate([truncated], [frame(obj(box=(0, 100, 80, 200), score=0.9))], ("Car",))
    assert ap(r, "AP11", "Car", "bbox") == pytest.approx([0.0, 0.0, 100 / 11])
    # exactly 40 px tall counts for Easy (the C++ devkit's `height < 40`)
    tall40 = frame(obj(box=(0, 100, 80, 140)))
    r = ke.evaluate([tall40], [frame(obj(box=(0, 100, 80, 140), score=0.9))], ("Car",))
    assert ap(r, "AP11", "Car", "bbox")[0] == pytest.approx(100 / 11)


def test_low_detections_are_ignored_not_false_positives():
    """A detection under the minimum height is neither TP nor FP, and it shields the object it covers."""
    gts, preds = _many_cars(extra_pred=[obj(box=(2000, 100, 2100, 130), loc=(-40.0, 1.5, 30.0), score=0.99)])
    r = ke.evaluate(gts, preds, classes=("Car",))
    assert ap(r, "AP40", "Car", "bbox")[0] == pytest.approx(100.0)  # Easy: 30 px < 40: ignored
    assert ap(r, "AP40", "Car", "bbox")[1] < 100.0  # Moderate: 30 px counts: a FP


def test_missing_prediction_file_means_no_detections(tmp_path):
    gt_dir, pred_dir = tmp_path / "gt", tmp_path / "pred"
    gt_dir.mkdir()
    pred_dir.mkdir()
    line = "Car 0.00 0 -1.67 657.39 150.13 700.07 223.39 1.41 1.58 4.36 3.18 2.27 34.38 -1.58"
    (gt_dir / "000000.txt").write_text(line + "\n")
    (gt_dir / "000001.txt").write_text(line + "\n")
    (pred_dir / "000000.txt").write_text(line + " 0.9\n")
    r = ke.evaluate_folders(gt_dir, pred_dir)
    # 2 valid cars, one found: one threshold, recall 1/2, precision 1 at position 0 -> AP11 = 1/11
    assert ap(r, "AP11", "Car", "bbox") == pytest.approx([100 / 11] * 3)
    assert ap(r, "AP40", "Car", "3d") == pytest.approx([0.0] * 3)
    ids, gts, preds = ke.read_folders(gt_dir, pred_dir)
    assert ids == ["000000", "000001"] and len(preds[1]) == 0
    ids_file = tmp_path / "val.txt"
    ids_file.write_text("000000\n\n")
    assert ke.read_ids(ids_file) == ["000000"]
    with pytest.raises(FileNotFoundError, match="000009"):
        ke.evaluate_folders(gt_dir, pred_dir, ids=["000009"])


@pytest.mark.parametrize("text, with_score, match", [
    ("Car 0.00 0 -1.67 657.39 190.13 700.07 223.39 1.41 1.58 4.36 3.18 2.27 34.38\n", False, r"x\.txt:1: .*found 14"),
    ("\nCar 0.00 0 -1.67 657.39 190.13 700.07 223.39 1.41 1.58 4.36 3.18 2.27 34.38 -1.58\n", True,
     r"x\.txt:2: a prediction line has 16 fields"),
    ("Car 0.00 0 -1.67 657.39 abc 700.07 223.39 1.41 1.58 4.36 3.18 2.27 34.38 -1.58\n", False,
     r"x\.txt:1: field 'bbox_top' is not a number: 'abc'"),
    ("Car 0.00 0 -1.67 657.39 190 700.07 223.39 1.41 1.58 4.36 3.18 2.27 34.38 -1.58 nan\n", True,
     r"x\.txt:1: field 'score' is not finite"),
])
def test_bad_label_lines_name_file_line_and_field(text, with_score, match):
    with pytest.raises(ke.KittiFormatError, match=match):
        ke.parse_labels(text, "x.txt", with_score)


def test_bad_prediction_file_in_a_folder_is_named(tmp_path):
    (tmp_path / "gt").mkdir()
    (tmp_path / "pred").mkdir()
    (tmp_path / "gt" / "000004.txt").write_text("")
    (tmp_path / "pred" / "000004.txt").write_text("Car 0 0 0 1 2 3 4 1 1 1 1 1 1 zero 0.5\n")
    with pytest.raises(ke.KittiFormatError, match=r"000004\.txt:1: field 'rotation_y'"):
        ke.evaluate_folders(tmp_path / "gt", tmp_path / "pred")


def test_command_prints_the_table_and_writes_json(tmp_path, capsys):
    gt_dir, pred_dir = tmp_path / "gt", tmp_path / "pred"
    gt_dir.mkdir()
    pred_dir.mkdir()
    line = "Pedestrian 0.00 0 -0.20 712.40 143.00 810.73 307.92 1.89 0.48 1.20 1.84 1.47 8.41 0.01"
    for k in range(3):
        (gt_dir / f"00000{k}.txt").write_text(line + "\n")
        (pred_dir / f"00000{k}.txt").write_text(line + " 0.8\n")
    parser = argparse.ArgumentParser()
    kitti_eval_command.add_arguments(parser)
    out = tmp_path / "res" / "kitti.json"
    args = parser.parse_args(["--gt", str(gt_dir), "--pred", str(pred_dir), "--out", str(out)])
    assert kitti_eval_command.run(args) == 0
    printed = capsys.readouterr().out
    assert "AP40" in printed and "Pedestrian" in printed
    data = json.loads(out.read_text())
    # 3 valid pedestrians, all found: AP40 = 2/40, AP11 = 1/11
    assert data["AP40"]["Pedestrian"]["3d"] == pytest.approx([5.0] * 3)
    assert data["AP11"]["Pedestrian"]["bbox"] == pytest.approx([100 / 11] * 3)
    assert list(data) == ["omnigen", "AP40", "AP11"]  # the mark first: a rerun may replace the file
    args = parser.parse_args(["--gt", str(tmp_path / "nope"), "--pred", str(pred_dir)])
    assert kitti_eval_command.run(args) == 2


# ---------------------------------------------------------------------------------------------
# real KITTI labels
# ---------------------------------------------------------------------------------------------


def test_real_kitti_labels_against_themselves(tmp_path):
    if not REAL_LABELS.is_dir():
        pytest.skip(f"real KITTI labels not found at {REAL_LABELS} (../shared/realdata beside the checkout)")
    pred_dir = tmp_path / "pred"
    pred_dir.mkdir()
    for f in sorted(REAL_LABELS.glob("*.txt")):
        lines = [ln + " 1.0" for ln in f.read_text().splitlines() if ln.strip()]
        (pred_dir / f.name).write_text("\n".join(lines) + "\n")
    r = ke.evaluate_folders(REAL_LABELS, pred_dir)
    # The sample holds one valid pedestrian (164 px, all levels), one valid car (33 px: Moderate and
    # Hard; the other car is 21.6 px) and a cyclist with occlusion 3 (never valid). One object found
    # gives one threshold: AP11 = 1/11, AP40 = 0 (position 0 is not among R40's), as the devkit says.
    one = 100 / 11
    want11 = {"Car": [0.0, one, one], "Pedestrian": [one] * 3, "Cyclist": [0.0] * 3}
    for cls in ke.CLASSES:
        for metric in ke.METRICS:
            assert r["AP11"][cls][metric] == pytest.approx(want11[cls]), (cls, metric)
            assert r["AP40"][cls][metric] == pytest.approx([0.0] * 3), (cls, metric)
    # many copies of the sample (45 valid pedestrians, more than 41): GT against itself is 100
    gt_many, pred_many = tmp_path / "gt_many", tmp_path / "pred_many"
    gt_many.mkdir()
    pred_many.mkdir()
    for k in range(45):
        for f in sorted(REAL_LABELS.glob("*.txt")):
            (gt_many / f"{k:03d}{f.name}").write_text(f.read_text())
            (pred_many / f"{k:03d}{f.name}").write_text((pred_dir / f.name).read_text())
    r = ke.evaluate_folders(gt_many, pred_many)
    for kind in ("AP40", "AP11"):
        for metric in ke.METRICS:
            assert r[kind]["Pedestrian"][metric] == pytest.approx([100.0] * 3), (kind, metric)
            assert r[kind]["Car"][metric] == pytest.approx([0.0, 100.0, 100.0]), (kind, metric)
