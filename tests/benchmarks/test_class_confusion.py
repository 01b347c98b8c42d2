"""benchmarks/class_confusion.py: what class each test object was found as, blind-matched by box."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest

from benchmarks import class_confusion
from omnigen.dataset import Dataset
from omnigen.fakes import write_fake_dataset
from omnigen.taxonomy import load_taxonomy


@pytest.fixture(scope="module")
def fake(tmp_path_factory):
    root = tmp_path_factory.mktemp("fake")
    write_fake_dataset(root, 3, objects_per_frame=4, seed=7)
    return Dataset.open(root, show_progress=False)


def _pred(fid, box, cat, score=0.9):
    x0, y0, x1, y1 = (float(v) for v in box)
    return {"frame_id": fid, "bbox": [x0, y0, x1 - x0, y1 - y0], "category_id": cat, "score": score,
            "keypoints": [0.0] * 24}


def test_each_object_counts_as_the_class_of_its_best_box_match_or_as_not_found(fake):
    tax = load_taxonomy("fine")
    classes, fine = tax.classes, tax.fine_class_ids()
    fid = str(fake.table.frame_id[0])
    o = fake.objects
    rows = [r for r in range(int(fake.offsets[0]), int(fake.offsets[1])) if not o.behind_camera[r].any()]
    a, b, c = rows[:3]
    ca, cb = int(fine[o.category[a]]), int(fine[o.category[b]])
    wrong = (cb + 1) % len(classes)
    preds = [_pred(fid, o.bbox[a], ca + 1),  # a: found as itself
             _pred(fid, o.bbox[b], wrong + 1, 0.8), _pred(fid, o.bbox[b], cb + 1, 0.1),  # b: the low score is ignored
             _pred(fid, o.bbox[c] + np.array([500, 500, 500, 500]), 1)]  # c: no overlap, not found
    table = class_confusion.confusion(fake, preds, classes, fine, [fid])
    assert table[classes[ca]][classes[ca]] >= 1
    assert table[classes[cb]][classes[wrong]] >= 1
    assert sum(table[name][None] for name in classes) == len(rows) - 2  # every other object: not found
    assert sum(sum(t.values()) for t in table.values()) == len(rows)


def test_rows_and_the_summary_line_separate_rare_classes():
    table = {"car": Counter({"car": 8, "van": 1, None: 1}), "cyclist": Counter({"pedestrian": 2, None: 3}),
             "tram": Counter()}
    rows = class_confusion.rows_of(table, {"car": 500, "cyclist": 40, "tram": 10})
    assert [r["class"] for r in rows] == ["car", "cyclist"]  # no test objects: no row
    assert rows[1] == {"class": "cyclist", "train": 40, "objects": 5, "as_itself": 0, "as_other": 2,
                       "top_other": "pedestrian", "top_other_count": 2, "not_found": 3}
    assert class_confusion.summary(rows) == ("class confusion: found 11 of 15 objects, 3 of them as another class; "
                                             "rare classes (under 130 training instances) found 2 of 5, 2 as another class")


def test_main_loads_once_and_asks_for_the_one_class_each_detection_was_given(fake, monkeypatch, capsys):
    import omnigen.detector.predict as predict
    import omnigen.splits as splits

    state, seen = {"taxonomy": load_taxonomy("fine").to_dict()}, []
    monkeypatch.setattr(predict, "load_for_prediction", lambda weights, device: seen.append("load") or ("m", state))
    monkeypatch.setattr(predict, "predict_split", lambda model, st, root, **kw: seen.append(kw["multi_label"]) or [])
    monkeypatch.setattr(splits, "read_split", lambda root, name: list(fake.table.frame_id))
    monkeypatch.setattr(class_confusion, "train_counts", lambda dataset, taxonomy: {})
    assert class_confusion.main(["w.pt", str(fake.root), "--device", "cpu"]) == 0
    assert seen == ["load", False]  # single-label: the multi-label protocol would give a box every class
    assert capsys.readouterr().out.strip().splitlines()[-1].startswith("class confusion: found 0 of ")
