"""omnigen eval: OKS metrics per group, best-F1 precision/recall, adherence, prediction checks, the command."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from pycocotools.cocoeval import COCOeval

import omnigen.detector.evaluation.oks_eval as oks_eval
from omnigen.detector import eval_command
from omnigen.detector.evaluation.oks_eval import (PredictionError, _coco_from_dict, _results_coco, ap_numbers, best_f1,
                               evalimgs_subset, evaluate, make_cocoeval, normalize_predictions, run_quietly)
from omnigen.formats.coco import to_coco
from omnigen.dataset import Dataset
from omnigen.fakes import write_fake_dataset
from omnigen.merge import merge
from omnigen.splits import read_split
from omnigen.taxonomy import load_taxonomy


@pytest.fixture(scope="module")
def ds(tmp_path_factory) -> Dataset:
    """Synthetic (three views) and kitti frames, merged, with train and test splits."""
    root = tmp_path_factory.mktemp("eval")
    syn = write_fake_dataset(root / "syn", n_frames=60, objects_per_frame=5, seed=11).root
    kit = write_fake_dataset(root / "kit", n_frames=30, objects_per_frame=5, seed=12, source="kitti").root
    merge([syn, kit], root / "uov", test_fraction=0.3, seed=1)
    return Dataset.open(root / "uov", show_progress=False)


def perfect(ds: Dataset, split: str | None = "test", by: str = "frame_id") -> list[dict]:
    """Every ground-truth object of the split predicted at its true corners (all eight), score 0.9.

    Objects with no corner in the image are left out: COCO ignores them as ground truth, and a
    detection of one is only forgiven when its corners fall in twice the object's clipped 2D box.
    """
    keep = None if split is None else set(read_split(ds.root, split))
    coco = to_coco(ds)  # fine taxonomy: one annotation per object, object order
    frames = {im["id"]: im["frame_id"] for im in coco["images"]}
    out = []
    for a, kp in zip(coco["annotations"], ds.objects.keypoints):
        fid = frames[a["image_id"]]
        if (keep is not None and fid not in keep) or a["num_keypoints"] == 0:
            continue
        xyv = np.concatenate([np.nan_to_num(kp), np.full((8, 1), 2.0)], axis=1)
        p = {"category_id": a["category_id"], "keypoints": xyv.ravel().tolist(), "score": 0.9, "bbox": a["bbox"]}
        p["frame_id" if by == "frame_id" else "image_id"] = fid if by == "frame_id" else a["image_id"]
        out.append(p)
    return out


def noisy(preds: list[dict], rng: np.random.Generator, px: float) -> list[dict]:
    out = []
    for p in preds:
        kp = np.asarray(p["keypoints"]).reshape(8, 3)
        kp[:, :2] += rng.normal(0, px, (8, 2))
        out.append({**p, "keypoints": kp.ravel().tolist(), "score": float(rng.uniform(0.1, 1.0))})
    return out


def plain_cocoeval(gt, dt, img_ids=None, cat_ids=None, area_rng=oks_eval.AREA_ALL):
    """pycocotools' own COCOeval (no subclass) with the module's parameters: the reference."""
    e = COCOeval(gt, dt, iouType="keypoints")
    e.params.kpt_oks_sigmas = np.full(8, oks_eval.OKS_SIGMA)
    e.params.maxDets = [oks_eval.MAX_DETS]
    e.params.areaRng, e.params.areaRngLbl = [list(area_rng)], ["range"]
    if img_ids is not None:
        e.params.imgIds = sorted(img_ids)
    if cat_ids is not None:
        e.params.catIds = list(cat_ids)
    run_quietly(e.evaluate)
    run_quietly(e.accumulate)
    return e


def coco_pair(ds: Dataset, preds: list[dict]):
    """The whole dataset's ground truth (dict and COCO) and the predictions as a COCO results object."""
    gt_dict = to_coco(ds)
    gt = _coco_from_dict(gt_dict)
    anns, _ = normalize_predictions(preds, ds, {im["id"] for im in gt_dict["images"]}, len(gt_dict["categories"]))
    return gt_dict, gt, _results_coco(gt, anns)


def test_perfect_predictions_score_one_in_every_group(ds):
    report = evaluate(ds, perfect(ds), split="test", adherence=False)
    groups = {r.group for r in report.rows}
    assert {"overall", "source=synthetic", "source=kitti", "view=ego", "view=aerial"} <= groups
    n_test = len(read_split(ds.root, "test"))
    assert report.row("overall").images == n_test
    for r in report.rows:
        assert r.objects > 0
        assert (r.oks_map50_95, r.ap_oks50, r.precision, r.recall, r.f1) == pytest.approx((1, 1, 1, 1, 1)), r.group
        assert r.conf_threshold == pytest.approx(0.9)
    assert report.row("source=synthetic").images + report.row("source=kitti").images == n_test


def test_noise_lowers_the_numbers_more_the_more_noise(ds):
    rng = np.random.default_rng(0)
    base = perfect(ds)
    small = evaluate(ds, noisy(base, rng, 1.0), split="test", adherence=False).row("overall")
    large = evaluate(ds, noisy(base, rng, 6.0), split="test", adherence=False).row("overall")
    assert small.oks_map50_95 < 1.0
    assert large.oks_map50_95 < small.oks_map50_95
    assert large.recall < 1.0 and large.f1 < small.f1 + 1e-9


def test_confident_false_positive_sets_precision_as_by_hand(ds):
    preds = perfect(ds)
    coco = to_coco(ds, "test")
    counted = [a for a in coco["annotations"] if a["num_keypoints"] > 0]
    n = len(counted)
    victim = dict(preds[0])
    kp = np.asarray(victim["keypoints"]).reshape(8, 3)
    kp[:, :2] += 5000.0  # far from everything: matches nothing
    fp = {**victim, "keypoints": kp.ravel().tolist(), "score": 0.99}
    r = evaluate(ds, preds + [fp], split="test", adherence=False).row("overall")
    # Above 0.99 nothing; at 0.9: n TPs and the one FP, F1 = 2n / (2n + 1), the best threshold.
    assert r.conf_threshold == pytest.approx(0.9)
    assert r.precision == pytest.approx(n / (n + 1))
    assert r.recall == pytest.approx(1.0)
    assert r.f1 == pytest.approx(2 * n / (2 * n + 1))
    # AP50: the FP ranks first in its class, whose envelope precision is nc / (nc + 1) at every recall.
    cat = fp["category_id"]
    per_cat = {}
    for a in counted:
        per_cat[a["category_id"]] = per_cat.get(a["category_id"], 0) + 1
    nc = per_cat[cat]
    expected = (len(per_cat) - 1 + nc / (nc + 1)) / len(per_cat)
    assert r.ap_oks50 == pytest.approx(expected)
    # The same FP below every TP costs nothing at the best threshold.
    low = evaluate(ds, preds + [{**fp, "score": 0.1}], split="test", adherence=False).row("overall")
    assert (low.precision, low.recall, low.conf_threshold) == pytest.approx((1.0, 1.0, 0.9))


def test_groups_equal_a_separate_restricted_cocoeval(ds):
    preds = noisy(perfect(ds, split=None), np.random.default_rng(3), 3.0)
    report = evaluate(ds, preds, split=None, adherence=False)
    gt_dict, gt, dt = coco_pair(ds, preds)
    checked = 0
    for key in ("source", "view"):
        for name in {im[key] for im in gt_dict["images"]}:
            ids = [im["id"] for im in gt_dict["images"] if im[key] == name]
            e = plain_cocoeval(gt, dt, ids)
            alone = ap_numbers(e.eval["precision"])
            f = best_f1(e.evalImgs)
            row = report.row(f"{key}={name}")
            assert (row.oks_map50_95, row.ap_oks50) == pytest.approx(alone, abs=1e-12)
            assert (row.precision, row.recall, row.f1, row.conf_threshold) == \
                pytest.approx((f.precision, f.recall, f.f1, f.conf_threshold), abs=1e-12)
            assert 0 < row.oks_map50_95 < 1
            checked += 1
    assert checked >= 5


def noisy_report_rows(ds: Dataset, seed: int, prefix: str):
    """Noisy predictions on every frame, their report's rows starting with `prefix`, and the COCO pair."""
    preds = noisy(perfect(ds, split=None), np.random.default_rng(seed), 3.0)
    report = evaluate(ds, preds, split=None, adherence=False)
    return report, [r for r in report.rows if r.group.startswith(prefix)], *coco_pair(ds, preds)


def assert_row_equals_reference(row, e: COCOeval) -> None:
    """mAP, AP50, objects, precision and recall of a report row equal those of a reference COCOeval."""
    assert (row.oks_map50_95, row.ap_oks50) == pytest.approx(ap_numbers(e.eval["precision"]), abs=1e-12)
    f = best_f1(e.evalImgs)
    assert (row.objects, row.precision, row.recall) == (f.objects, pytest.approx(f.precision), pytest.approx(f.recall))


def test_class_rows_equal_pycocotools_per_category_and_average_to_the_map(ds):
    report, rows, gt_dict, gt, dt = noisy_report_rows(ds, 5, "class=")
    assert len(rows) >= 3
    for row in rows:
        cat = next(c["id"] for c in gt_dict["categories"] if f"class={c['name']}" == row.group)
        assert_row_equals_reference(row, plain_cocoeval(gt, dt, cat_ids=[cat]))
        assert row.images == len({a["image_id"] for a in gt.loadAnns(gt.getAnnIds(catIds=[cat])) if a["num_keypoints"]})
    overall = report.row("overall")
    assert sum(r.objects for r in rows) == overall.objects
    assert np.mean([r.oks_map50_95 for r in rows]) == pytest.approx(overall.oks_map50_95, abs=1e-12)


def test_size_rows_equal_pycocotools_area_ranges_and_cover_every_object(ds):
    report, rows, gt_dict, gt, dt = noisy_report_rows(ds, 6, "size=")
    assert len(rows) >= 2
    sizes = [math.sqrt(a["area"]) for a in gt_dict["annotations"] if a["num_keypoints"]]
    for row in rows:
        lo, hi = oks_eval.SIZE_BINS[row.group[5:]]
        assert_row_equals_reference(row, plain_cocoeval(gt, dt, area_rng=[lo ** 2, hi ** 2]))  # the bin alone
        assert row.objects == sum(lo <= v <= hi for v in sizes)
    assert sum(r.objects for r in rows) == report.row("overall").objects  # the bins part every object
    # a prediction of every small object alone: the tiny and small rows are perfect, the others empty-handed
    small = [p for p, a in zip(perfect(ds, split=None), [a for a in gt_dict["annotations"] if a["num_keypoints"]])
             if math.sqrt(a["area"]) < 32]
    by_size = {r.group: r for r in evaluate(ds, small, split=None, adherence=False).rows}
    assert by_size["size=tiny"].oks_map50_95 == pytest.approx(1.0) and by_size["size=small"].recall == pytest.approx(1.0)
    assert by_size["size=medium"].recall == 0.0 and math.isnan(by_size["size=medium"].precision)  # no detection there


def test_training_validation_skips_the_size_rows(ds):
    assert all(not r.group.startswith("size=") for r in evaluate(ds, perfect(ds), "test", adherence=False, sizes=False).rows)


def test_subset_accumulate_matches_pycocotools_precision_array(ds):
    preds = noisy(perfect(ds, split=None), np.random.default_rng(4), 2.0)
    gt_dict, gt, dt = coco_pair(ds, preds)
    full = make_cocoeval(gt, dt)
    run_quietly(full.evaluate)
    ids = [im["id"] for im in gt_dict["images"] if im["view"] == "aerial"]
    _, sub = evalimgs_subset(full, ids)
    run_quietly(sub.accumulate)
    alone = plain_cocoeval(_coco_from_dict(to_coco(ds)), dt, ids)
    np.testing.assert_array_equal(sub.eval["precision"], alone.eval["precision"])


def test_frame_ids_win_over_image_ids_and_outside_split_is_counted(ds):
    by_image = evaluate(ds, perfect(ds, by="image_id"), split="test", adherence=False)
    wrong_ids = [{**p, "image_id": 1} for p in perfect(ds)]  # frame_id present: image_id ignored
    by_frame = evaluate(ds, wrong_ids, split="test", adherence=False)
    assert [r.__dict__ for r in by_frame.rows] == [r.__dict__ for r in by_image.rows]
    everything = evaluate(ds, perfect(ds, split=None), split="test", adherence=False)
    assert everything.predictions == by_frame.predictions
    assert everything.predictions_outside_split == len(perfect(ds, split="train")) > 0
    assert everything.row("overall").f1 == pytest.approx(1.0)


@pytest.mark.parametrize("change, field", [
    (lambda p: p.pop("keypoints"), "keypoints"),
    (lambda p: p.update(keypoints=p["keypoints"][:21]), "keypoints"),
    (lambda p: p.update(keypoints=[math.nan] * 24), "keypoints"),
    (lambda p: (p.pop("frame_id"), p.update(image_id=10 ** 6)), "image_id"),
    (lambda p: p.update(frame_id="no-such-frame"), "frame_id"),
    (lambda p: p.update(category_id=99), "category_id"),
    (lambda p: p.pop("score"), "score"),
])
def test_bad_predictions_name_the_file_and_field(ds, change, field):
    preds = perfect(ds)[:3]
    change(preds[1])
    with pytest.raises(PredictionError, match=rf"preds\.json: prediction 1: field '{field}'"):
        evaluate(ds, preds, split="test", adherence=False, source="preds.json")


def test_adherence_means_per_group_with_a_stub_lift(ds, monkeypatch):
    """The adherence plumbing against omnigen.detector.bev.lift's API, whatever the lift computes."""
    calls = {}

    class Priors:
        def dims_for(self, names):
            return np.ones((len(names), 3))

    def fit_dimension_priors(dataset, frame_ids):
        calls["frames"] = list(frame_ids)
        return Priors()

    def lift_keypoints(keypoints, dims, K, valid=None):
        return SimpleNamespace(ok=np.ones(len(keypoints), bool))

    # Every fake frame has its own random ground plane: the stub tells the sources apart by it.
    kitti_planes = {ds.table.ground_plane[i].tobytes() for i, s in enumerate(ds.table.source) if s == "kitti"}

    def ground_adherence_deg(lifted, plane):
        return np.full(len(lifted.ok), 1.0 if np.asarray(plane).tobytes() in kitti_planes else 3.0)

    stub = SimpleNamespace(fit_dimension_priors=fit_dimension_priors, lift_keypoints=lift_keypoints,
                           ground_adherence_deg=ground_adherence_deg)
    monkeypatch.setitem(__import__("sys").modules, "omnigen.detector.bev.lift", stub)
    report = evaluate(ds, perfect(ds), split="test")
    assert calls["frames"] == read_split(ds.root, "train")
    assert report.priors_from == "train"
    assert report.row("source=kitti").ground_adherence_deg == pytest.approx(1.0)
    assert report.row("source=synthetic").ground_adherence_deg == pytest.approx(3.0)
    k, s = report.row("source=kitti"), report.row("source=synthetic")
    overall = report.row("overall")
    assert overall.adherence_objects == k.adherence_objects + s.adherence_objects == overall.objects
    assert overall.ground_adherence_deg == pytest.approx((k.adherence_objects + 3 * s.adherence_objects) /
                                                         overall.adherence_objects)


def test_priors_from_all_frames_without_a_train_split_and_no_plane_no_adherence(tmp_path, monkeypatch):
    small = write_fake_dataset(tmp_path / "small", n_frames=6, objects_per_frame=3, seed=7, images=False)
    calls = {}

    def fit_dimension_priors(dataset, frame_ids):
        calls["frames"] = list(frame_ids)
        return SimpleNamespace(dims_for=lambda names: np.ones((len(names), 3)))

    stub = SimpleNamespace(
        fit_dimension_priors=fit_dimension_priors,
        lift_keypoints=lambda kp, dims, K, valid=None: SimpleNamespace(ok=np.ones(len(kp), bool)),
        ground_adherence_deg=lambda lifted, plane: np.full(len(lifted.ok), 2.0))
    monkeypatch.setitem(__import__("sys").modules, "omnigen.detector.bev.lift", stub)
    report = evaluate(small, perfect(small, split=None), split=None)
    assert report.priors_from == "all frames" and calls["frames"] == small.table.frame_id
    assert report.row("overall").ground_adherence_deg == pytest.approx(2.0)
    small.table.ground_plane[:] = np.nan  # ground plane unknown everywhere: nothing to report
    unknown = evaluate(small, perfect(small, split=None), split=None)
    assert math.isnan(unknown.row("overall").ground_adherence_deg) and unknown.row("overall").adherence_objects == 0
    assert unknown.to_dict()["rows"][0]["ground_adherence_deg"] is None


def test_adherence_with_the_real_lift_is_small_for_true_corners(ds):
    report = evaluate(ds, perfect(ds), split="test")
    r = report.row("overall")
    assert r.adherence_objects > 0.8 * r.objects
    assert 0.0 <= r.ground_adherence_deg < 5.0  # true corners, median class sizes: nearly flat bottoms
    noisy_r = evaluate(ds, noisy(perfect(ds), np.random.default_rng(1), 3.0), split="test").row("overall")
    assert noisy_r.ground_adherence_deg > r.ground_adherence_deg


def _args(tmp_path: Path, predictions: Path, dataset: Path, **kw) -> argparse.Namespace:
    p = argparse.ArgumentParser()
    eval_command.add_arguments(p)
    argv = [str(predictions), str(dataset), "--out", str(tmp_path / "report.json")]
    for k, v in kw.items():
        argv += [f"--{k.replace('_', '-')}"] + ([] if v is True else [str(v)])
    return p.parse_args(argv)


def test_command_writes_json_and_prints_a_table(ds, tmp_path, capsys, monkeypatch):
    from omnigen import progress

    monkeypatch.setattr(progress.console, "_width", 200)  # no column folding in the captured table
    path = tmp_path / "preds.json"
    path.write_text(json.dumps(perfect(ds)))
    assert eval_command.run(_args(tmp_path, path, ds.root, no_adherence=True)) == 0
    out = capsys.readouterr().out
    assert "overall" in out and "source=kitti" in out
    doc = json.loads((tmp_path / "report.json").read_text())
    assert doc["arguments"]["split"] == "test" and doc["wall_s"] >= 0
    rows = {r["group"]: r for r in doc["report"]["rows"]}
    assert rows["overall"]["f1"] == pytest.approx(1.0)
    assert "size=small" in rows and "size=small" in out
    assert eval_command.run(_args(tmp_path, path, ds.root, no_adherence=True, no_sizes=True)) == 0
    doc = json.loads((tmp_path / "report.json").read_text())
    assert not any(r["group"].startswith("size=") for r in doc["report"]["rows"])


def test_command_runs_weights_through_predict(ds, tmp_path, monkeypatch):
    import omnigen.detector.prediction.predict as predict

    seen, state = {}, {"taxonomy": load_taxonomy("fine").to_dict()}

    def fake_load(weights, device):
        seen.update(weights=Path(weights), device=device, loads=seen.get("loads", 0) + 1)
        return "model", state

    def fake_predict(model, got_state, root, split, imgsz, batch, multi_label, vertical):
        assert (model, got_state) == ("model", state)
        seen.update(split=split, imgsz=imgsz, batch=batch, multi_label=multi_label, vertical=vertical)
        return perfect(ds)

    monkeypatch.setattr(predict, "load_for_prediction", fake_load)
    monkeypatch.setattr(predict, "predict_split", fake_predict)
    weights = tmp_path / "best.pt"
    weights.write_bytes(b"x")
    args = _args(tmp_path, weights, ds.root, imgsz=320, batch=2, no_adherence=True, device="cpu")
    assert eval_command.run(args) == 0
    assert seen == {"weights": weights, "split": "test", "imgsz": 320, "batch": 2, "device": "cpu", "loads": 1,
                    "multi_label": True, "vertical": None}  # every class above the floor, as Ultralytics' validation;
    # no --vertical: predict_split takes the run's predict.vertical (trained_vertical)
    assert eval_command.run(_args(tmp_path, weights, ds.root, imgsz=320, batch=2, no_adherence=True,
                                  device="cpu", single_label=True, vertical="off")) == 0
    assert seen["multi_label"] is False and seen["vertical"] == "off"


def test_command_refuses_single_label_for_predictions_made_already(ds, tmp_path, capsys):
    path = tmp_path / "preds.json"
    path.write_text(json.dumps(perfect(ds)))
    assert eval_command.run(_args(tmp_path, path, ds.root, single_label=True)) == 2
    err = capsys.readouterr().err
    assert "preds.json" in err and "--single-label" in err
    assert not (tmp_path / "report.json").exists()


def test_command_bad_input_exits_2_naming_file_and_field(ds, tmp_path, capsys):
    assert eval_command.run(_args(tmp_path, tmp_path / "missing.json", ds.root)) == 2
    assert "missing.json" in capsys.readouterr().err
    bad = tmp_path / "bad.json"
    preds = perfect(ds)[:2]
    del preds[1]["keypoints"]
    bad.write_text(json.dumps(preds))
    assert eval_command.run(_args(tmp_path, bad, ds.root)) == 2
    err = capsys.readouterr().err
    assert "bad.json" in err and "'keypoints'" in err
    assert not (tmp_path / "report.json").exists()


# ---------------------------------------------------------------------------------------------
# Corner errors of box-matched objects
# ---------------------------------------------------------------------------------------------


def truth_of(ds: Dataset, split: str | None = "test") -> list[dict]:
    """The annotations perfect(ds, split) predicts, in its order."""
    return [a for a in to_coco(ds, split)["annotations"] if a["num_keypoints"]]


def shifted(preds: list[dict], offsets: np.ndarray) -> list[dict]:
    """Every corner of prediction k moved by offsets[k] (2,) or offsets[k] (8, 2); boxes kept."""
    out = []
    for p, d in zip(preds, offsets):
        kp = np.asarray(p["keypoints"], dtype=float).reshape(8, 3)
        kp[:, :2] += d
        out.append({**p, "keypoints": kp.ravel().tolist()})
    return out


def expected_medians(truth: list[dict], err: np.ndarray) -> tuple[float, float]:
    """Median px and px / sqrt(area) over the labelled corners, each object's error err[k] on all of them."""
    n = np.asarray([a["num_keypoints"] for a in truth])
    scale = np.sqrt([a["area"] for a in truth])
    return float(np.median(np.repeat(err, n))), float(np.median(np.repeat(err / scale, n)))


def test_corner_errors_of_known_offsets_per_row(ds):
    truth = truth_of(ds)
    k = np.arange(len(truth))
    err = 5.0 * (1 + k % 3)  # 3-4-5 triangles: 5, 10 and 15 px on every corner
    preds = shifted(perfect(ds), np.stack([0.6 * err, 0.8 * err], axis=1))
    report = evaluate(ds, preds, split="test", adherence=False)
    overall = report.row("overall")
    assert overall.corner_objects == len(truth) == overall.objects
    assert (overall.corner_error_px, overall.corner_error_rel) == pytest.approx(expected_medians(truth, err))
    views = {im["id"]: im["view"] for im in to_coco(ds, "test")["images"]}
    aerial = np.asarray([views[a["image_id"]] == "aerial" for a in truth])
    row = report.row("view=aerial")
    assert row.corner_objects == aerial.sum() > 0
    assert (row.corner_error_px, row.corner_error_rel) == pytest.approx(
        expected_medians([a for a, s in zip(truth, aerial) if s], err[aerial]))
    cat = truth[0]["category_id"]
    name = next(c["name"] for c in to_coco(ds)["categories"] if c["id"] == cat)
    of_cat = np.asarray([a["category_id"] == cat for a in truth])
    assert report.row(f"class={name}").corner_error_rel == pytest.approx(
        expected_medians([a for a, s in zip(truth, of_cat) if s], err[of_cat])[1])
    sizes = [r for r in report.rows if r.group.startswith("size=")]
    assert sum(r.corner_objects for r in sizes) == len(truth)
    assert report.row("overall").corner_errors_per_corner is None  # only when asked


def test_unmatched_and_wrong_class_predictions_leave_the_corner_errors(ds):
    truth = truth_of(ds)
    preds = shifted(perfect(ds), np.tile([3.0, 4.0], (len(truth), 1)))  # 5 px on every corner
    for p in preds[:4]:  # the box moved off its object: corners 60 px off, box IoU 0
        p["keypoints"] = (np.asarray(p["keypoints"]) + np.tile([60.0, 0.0, 0.0], 8)).tolist()
        p["bbox"] = [p["bbox"][0] + 1000, *p["bbox"][1:]]
    n_cat = len(to_coco(ds)["categories"])
    for p in preds[4:7]:  # the right box and far corners, the wrong class
        p["keypoints"] = (np.asarray(p["keypoints"]) + np.tile([60.0, 0.0, 0.0], 8)).tolist()
        p["category_id"] = p["category_id"] % n_cat + 1
    r = evaluate(ds, preds, split="test", adherence=False).row("overall")
    assert r.corner_objects == len(truth) - 7
    assert (r.corner_error_px, r.corner_error_rel) == pytest.approx(expected_medians(truth[7:], np.full(len(truth) - 7, 5.0)))
    nothing = evaluate(ds, preds[:4], split="test", adherence=False).row("overall")
    assert nothing.corner_objects == 0 and math.isnan(nothing.corner_error_px) and math.isnan(nothing.corner_error_rel)
    assert evaluate(ds, preds[:4], split="test", adherence=False).to_dict()["rows"][0]["corner_error_px"] is None


def test_box_matching_is_greedy_by_score_one_prediction_per_object(ds):
    truth = truth_of(ds)
    base = perfect(ds)
    good = shifted(base, np.tile([0.6, 0.8], (len(truth), 1)))  # 1 px
    bad = [{**p, "score": 0.5} for p in shifted(base, np.tile([6.0, 8.0], (len(truth), 1)))]  # 10 px, lower score
    r = evaluate(ds, bad + good, split="test", adherence=False).row("overall")
    assert r.corner_objects == len(truth) and r.corner_error_px == pytest.approx(1.0)
    first = [{**p, "score": 0.95} for p in bad]  # now the 10-px duplicates come first
    assert evaluate(ds, first + good, split="test", adherence=False).row("overall").corner_error_px == pytest.approx(10.0)


def test_per_corner_medians_when_asked(ds):
    truth = truth_of(ds)
    offsets = np.zeros((len(truth), 8, 2))
    offsets[:, 3] = [6.0, 8.0]  # corner 3 alone is 10 px off
    report = evaluate(ds, shifted(perfect(ds), offsets), split="test", adherence=False, per_corner=True)
    r = report.row("overall")
    assert r.corner_errors_per_corner == pytest.approx([0, 0, 0, 10.0, 0, 0, 0, 0])
    labelled3 = [a for a in truth if a["keypoints"][3 * 3 + 2] > 0]
    assert r.corner_errors_rel_per_corner[3] == pytest.approx(np.median([10.0 / math.sqrt(a["area"]) for a in labelled3]))
    assert r.corner_error_px == 0.0  # seven corners in eight are exact
    assert all(len(row.corner_errors_per_corner) == 8 for row in report.rows)


def test_prediction_without_a_box_is_matched_by_its_corners_and_a_bad_box_is_an_error(ds):
    preds = [{k: v for k, v in p.items() if k != "bbox"} for p in perfect(ds)]
    r = evaluate(ds, preds, split="test", adherence=False).row("overall")
    assert r.corner_objects > 0.8 * r.objects and r.corner_error_px == 0.0
    bad = perfect(ds)[:2]
    bad[1]["bbox"] = [0, 0, -3, 4]
    with pytest.raises(PredictionError, match=r"preds\.json: prediction 1: field 'bbox'"):
        evaluate(ds, bad, split="test", adherence=False, source="preds.json")


def test_command_prints_corner_errors_per_corner_and_the_baseline(ds, tmp_path, capsys, monkeypatch):
    from omnigen import progress

    monkeypatch.setattr(progress.console, "_width", 250)
    path = tmp_path / "preds.json"
    path.write_text(json.dumps(perfect(ds)))
    assert eval_command.run(_args(tmp_path, path, ds.root, no_adherence=True, no_sizes=True, per_corner=True,
                                  baseline=True)) == 0
    out = capsys.readouterr().out
    assert "err px" in out and "err rel" in out
    assert "corner 0" in out and "corner 7" in out
    comparison = out[out.index("model vs box-template baseline"):]
    assert "mAP50:95" in comparison and "corner_error_rel" in comparison
    doc = json.loads((tmp_path / "report.json").read_text())
    model = {r["group"]: r for r in doc["report"]["rows"]}
    base = {r["group"]: r for r in doc["baseline"]["rows"]}
    assert set(model) == set(base) and "view=aerial" in base
    assert model["overall"]["corner_error_px"] == 0.0 and base["overall"]["corner_error_px"] > 0.5
    assert base["overall"]["oks_map50_95"] < model["overall"]["oks_map50_95"] == pytest.approx(1.0)
    assert len(model["overall"]["corner_errors_per_corner"]) == 8
    assert doc["baseline_template"]["fitted_from"] == "train"
    assert any("box-template baseline" in n for n in doc["baseline"]["notes"])


def test_corner_spread_says_how_collapsed_the_predicted_layouts_are(ds):
    """Predicted corners pulled halfway to their centroid spread half as far as the truth (0.5);
    exact corners spread 1.0; a shift moves them without changing the spread."""
    from omnigen.detector.evaluation.corner_errors import spread_ratio

    gt = np.array([[[0, 0], [4, 0], [4, 2], [0, 2], [0, 0], [4, 0], [4, 2], [0, 2]]], dtype=float)
    labelled = np.ones((1, 8), bool)
    centre = gt[0].mean(0)
    assert spread_ratio(gt, gt, labelled)[0] == pytest.approx(1.0)
    assert spread_ratio(centre + 0.5 * (gt - centre), gt, labelled)[0] == pytest.approx(0.5)
    assert spread_ratio(gt + 7.0, gt, labelled)[0] == pytest.approx(1.0)
    two = labelled.copy()
    two[0, 2:] = False
    assert math.isnan(spread_ratio(gt, gt, two)[0])  # under three labelled corners: no layout

    preds = perfect(ds)
    for p in preds:  # every prediction's corners halfway to their centroid, its box kept
        k = np.asarray(p["keypoints"], dtype=float).reshape(8, 3)
        k[:, :2] = k[:, :2].mean(0) + 0.5 * (k[:, :2] - k[:, :2].mean(0))
        p["keypoints"] = k.ravel().tolist()
    overall = evaluate(ds, preds, split="test", adherence=False, sizes=False).row("overall")
    exact = evaluate(ds, perfect(ds), split="test", adherence=False, sizes=False).row("overall")
    assert exact.corner_spread == pytest.approx(1.0) and 0.4 < overall.corner_spread < 0.6


def test_layout_error_forgives_the_heading_and_only_the_heading(ds):
    """Predictions turned 180 degrees (the same eight points, front and rear labels swapped) have
    large corner errors but no layout error; a mirrored order (not a turn) is not forgiven."""
    from omnigen.conventions import FLIP_IDX, TURN_IDX

    def reorder(preds, order):
        out = []
        for p in preds:
            k = np.asarray(p["keypoints"], dtype=float).reshape(8, 3)
            out.append({**p, "keypoints": k[list(order)].ravel().tolist()})
        return out

    turned = evaluate(ds, reorder(perfect(ds), TURN_IDX), split="test", adherence=False, sizes=False).row("overall")
    assert turned.corner_error_rel > 0.1 and turned.layout_error_rel == pytest.approx(0.0)
    exact = evaluate(ds, perfect(ds), split="test", adherence=False, sizes=False).row("overall")
    assert exact.layout_error_rel == exact.corner_error_rel == pytest.approx(0.0)
    mirrored = evaluate(ds, reorder(perfect(ds), FLIP_IDX), split="test", adherence=False, sizes=False).row("overall")
    assert mirrored.layout_error_rel > 0.05
