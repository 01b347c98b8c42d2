"""The box-template baseline: fitting known layouts, falling back, placing, scoring beside the model."""

from __future__ import annotations

import json

import numpy as np
import pytest

from omnigen.detector.evaluation.box_template import (BoxTemplate, apply, evaluate_with_baseline, fit_box_template,
                                   training_frames)
from omnigen.detector.evaluation.oks_eval import PredictionError
from omnigen.formats.coco import to_coco
from omnigen.dataset import Dataset
from omnigen.fakes import write_fake_dataset
from omnigen.splits import TRAIN, read_split, write_split
from omnigen.taxonomy import load_taxonomy

# A cuboid-like layout inside its box: top face higher and narrower than the bottom one.
LAYOUT = np.array([[-0.5, 0.1], [0.2, 0.3], [0.5, 0.5], [-0.2, 0.25],
                   [-0.45, -0.5], [0.15, -0.3], [0.4, -0.2], [-0.1, -0.4]])


def with_layouts(ds: Dataset, layout_of) -> Dataset:
    """Every object's corners replaced (in memory) by layout_of(fine class, view) placed into its box,
    all in the image and in front of the camera."""
    t = ds.objects
    views = np.asarray(ds.table.view)[t.frame]
    box = t.bbox
    wh = box[:, 2:] - box[:, :2]
    layouts = np.stack([layout_of(int(c), str(v)) for c, v in zip(t.category, views)])
    t.keypoints[:] = (box[:, None, :2] + box[:, None, 2:]) / 2 + layouts * wh[:, None, :]
    t.in_image[:] = True
    t.behind_camera[:] = False
    return ds


def split_in_two(ds: Dataset) -> tuple[list[str], list[str]]:
    ids = list(ds.table.frame_id)
    train, test = ids[: 2 * len(ids) // 3], ids[2 * len(ids) // 3:]
    write_split(ds.root, TRAIN, train)
    write_split(ds.root, "test", test)
    return train, test


@pytest.fixture
def small(tmp_path) -> Dataset:
    """36 frames (ego, infrastructure, aerial in turn) of 6 objects, no images."""
    return write_fake_dataset(tmp_path / "ds", n_frames=36, objects_per_frame=6, seed=5, images=False)


def pair_layout(c: int, view: str) -> np.ndarray:
    """A distinct layout per (fine class, view)."""
    return LAYOUT * (1 + 0.05 * c) + {"ego": 0.0, "infrastructure": 0.1, "aerial": -0.1}[view]


def test_fit_reproduces_each_pairs_layout_and_falls_back_to_class_and_overall(small):
    ds = with_layouts(small, pair_layout)
    fine = load_taxonomy("fine")
    t = fit_box_template(ds, None, fine, min_objects=1)
    assert t.fitted_from == "all frames" and t.frames == len(ds)
    views = np.asarray(ds.table.view)[ds.objects.frame]
    seen = 0
    for c, name in enumerate(fine.classes):
        for view in ("ego", "infrastructure", "aerial"):
            n = int(((ds.objects.category == c) & (views == view)).sum())
            if n:
                np.testing.assert_allclose(t.layout(name, view), pair_layout(c, view), atol=1e-9)
                assert t.by_class_view[name][view].counts.tolist() == [n] * 8
                seen += 1
            else:
                assert view not in t.by_class_view.get(name, {})
    assert seen >= 10
    # too few objects per pair: the class's mean over its views, then the mean of everything
    counts = {name: int((ds.objects.category == c).sum()) for c, name in enumerate(fine.classes)}
    name = max(counts, key=counts.get)
    c = fine.classes.index(name)
    pair_max = max(int(((ds.objects.category == c) & (views == v)).sum()) for v in ("ego", "infrastructure", "aerial"))
    assert pair_max < counts[name]
    by_class = fit_box_template(ds, None, fine, min_objects=pair_max + 1)
    mine = ds.objects.category == c
    want = np.mean([pair_layout(c, v) for v in views[mine]], axis=0)
    np.testing.assert_allclose(by_class.layout(name, "ego"), want, atol=1e-9)
    overall = fit_box_template(ds, None, fine, min_objects=10 ** 6)
    want = np.mean([pair_layout(int(k), v) for k, v in zip(ds.objects.category, views)], axis=0)
    np.testing.assert_allclose(overall.layout(name, "ego"), want, atol=1e-9)
    np.testing.assert_allclose(overall.layout("no-such-class", "no-such-view"), want, atol=1e-9)


def test_corners_behind_the_camera_are_left_out_and_frames_choose_the_objects(small):
    ds = with_layouts(small, lambda c, v: LAYOUT)
    t = ds.objects
    t.keypoints[0, 2] = np.nan  # corner 2 of the first object behind the camera
    t.behind_camera[0, 2] = True
    t.keypoints[1, 5] = [1e6, -1e6]  # far outside the image: still geometry, kept
    t.in_image[1, 5] = False
    fitted = fit_box_template(ds, None, "fine", min_objects=1)
    assert fitted.overall.counts[2] == len(t) - 1 and fitted.overall.counts[5] == len(t)
    np.testing.assert_allclose(fitted.overall.corners[2], LAYOUT[2], atol=1e-12)
    assert abs(fitted.overall.corners[5, 0] - LAYOUT[5, 0]) > 1.0
    train, _ = split_in_two(ds)
    only_train = fit_box_template(ds, TRAIN, "fine", min_objects=1)
    assert only_train.fitted_from == TRAIN and only_train.frames == len(train)
    assert only_train.overall.counts[0] == np.isin(t.frame, [ds.index_of(f) for f in train]).sum()
    assert training_frames(ds) == (read_split(ds.root, TRAIN), TRAIN)


def test_template_round_trips_through_json(small):
    t = fit_box_template(with_layouts(small, pair_layout), None, "fine", min_objects=2)
    back = BoxTemplate.from_dict(json.loads(json.dumps(t.to_dict())))
    assert back.to_dict() == t.to_dict()
    np.testing.assert_array_equal(back.layout("car", "aerial"), t.layout("car", "aerial"))


def true_box_predictions(ds: Dataset, split: str) -> list[dict]:
    """One prediction per counted object of the split: its true box and class, corners all at (0, 0)."""
    coco = to_coco(ds, split)
    frames = {im["id"]: im["frame_id"] for im in coco["images"]}
    return [{"frame_id": frames[a["image_id"]], "category_id": a["category_id"], "bbox": a["bbox"], "score": 0.8,
             "keypoints": [0.0] * 24} for a in coco["annotations"] if a["num_keypoints"]]


def test_apply_places_the_layout_into_each_box_and_keeps_the_rest(small):
    ds = with_layouts(small, lambda c, v: LAYOUT)
    t = fit_box_template(ds, None, "fine")
    preds = [{"frame_id": ds.table.frame_id[0], "category_id": 1, "bbox": [10.0, 20.0, 40.0, 10.0], "score": 0.7,
              "keypoints": [0.0] * 24, "extra": "kept"}]
    out = apply(t, preds, ds)
    kp = np.asarray(out[0]["keypoints"]).reshape(8, 3)
    np.testing.assert_allclose(kp[:, :2], np.array([30.0, 25.0]) + LAYOUT * [40.0, 10.0], atol=1e-9)
    assert {k: v for k, v in out[0].items() if k != "keypoints"} == {k: v for k, v in preds[0].items() if k != "keypoints"}
    assert preds[0]["keypoints"] == [0.0] * 24  # the input is not changed
    for field, change in (("bbox", lambda p: p.pop("bbox")), ("category_id", lambda p: p.update(category_id=99)),
                          ("frame_id", lambda p: p.update(frame_id="nope"))):
        bad = dict(preds[0])
        change(bad)
        with pytest.raises(PredictionError, match=rf"p\.json: prediction 0: field '{field}'"):
            apply(t, [bad], ds, source="p.json")


def test_baseline_in_the_true_boxes_of_one_layout_scores_near_perfect(small):
    ds = with_layouts(small, lambda c, v: LAYOUT)
    split_in_two(ds)
    preds = true_box_predictions(ds, "test")
    report, baseline = evaluate_with_baseline(ds, preds, "test", "fine", adherence=False, sizes=False)
    b, m = baseline.row("overall"), report.row("overall")
    assert b.objects == len(preds) and b.oks_map50_95 > 0.99 and b.corner_error_px < 1e-6
    assert m.oks_map50_95 < 0.05 and m.corner_error_px > 10  # the model's corners all at (0, 0)
    assert [r.group for r in baseline.rows] == [r.group for r in report.rows]
    assert "view=aerial" in {r.group for r in baseline.rows}
    assert "(train)" in baseline.notes[0] and len(baseline.notes) == 1


def test_baseline_of_turned_objects_is_worse_and_says_when_fitted_on_all_frames(small):
    ds = with_layouts(small, lambda c, v: LAYOUT)
    preds = true_box_predictions(ds, None)
    _, one = evaluate_with_baseline(ds, preds, None, "fine", adherence=False, sizes=False)
    assert "all frames" in one.notes[0] and "include the evaluated" in one.notes[1]
    assert one.row("overall").corner_error_rel < 1e-9
    turned = np.random.default_rng(0).random(len(ds.objects)) < 0.5  # half turned 180 degrees: no layout fits both
    ds.objects.keypoints[turned] = ds.objects.keypoints[turned][:, [2, 3, 0, 1, 6, 7, 4, 5]]
    _, mixed = evaluate_with_baseline(ds, preds, None, "fine", adherence=False, sizes=False)
    assert mixed.row("overall").corner_error_rel > 0.05 and mixed.row("overall").oks_map50_95 < 0.9


def test_a_model_that_predicts_nothing_gets_an_empty_baseline(small):
    """No predictions (a fresh model at any confidence floor): the baseline is empty too, and the
    evaluation runs on both, as gpu_validate's tiny run needs."""
    ds = with_layouts(small, lambda c, v: LAYOUT)
    assert apply(fit_box_template(ds, None, "fine"), [], ds) == []
    report, baseline = evaluate_with_baseline(ds, [], split=None, adherence=False, sizes=False)
    assert report.row("overall").oks_map50_95 == baseline.row("overall").oks_map50_95 == 0.0
