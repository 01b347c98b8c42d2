"""benchmarks/crop_stage_ablation.py: one crop-stage checkpoint scored with and without the stage's
corners, on a tiny fake dataset (the figures are meaningless; the plumbing is what is checked)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks import crop_stage_ablation  # noqa: E402
from omnigen.fakes import write_fake_dataset  # noqa: E402

def test_scores_the_same_detections_three_ways_and_writes_them(tmp_path, capsys, detector_checkpoint):
    root = tmp_path / "ds"
    write_fake_dataset(root, n_frames=3, objects_per_frame=3)
    out = tmp_path / "ablation.json"
    argv = [str(detector_checkpoint(tmp_path / "crop.pt", 16)), str(root), "--split", "all", "--imgsz", "64", "--device", "cpu",
            "--out", str(out)]
    assert crop_stage_ablation.main(argv) == 0
    printed = capsys.readouterr().out.strip().splitlines()
    assert printed[-1].startswith("crop stage: mAP50:95 ") and "head's corners" in printed[-1]
    assert any(line.startswith("| synthetic | head |") for line in printed)
    result = json.loads(out.read_text())
    assert result["detections"] > 0
    assert set(result) >= {"crop_stage", "head", "box_template"}
    assert result["crop_stage"].keys() == result["head"].keys() == result["box_template"].keys()


def test_a_checkpoint_without_a_crop_stage_is_refused(tmp_path, detector_checkpoint):
    root = tmp_path / "ds"
    write_fake_dataset(root, n_frames=1, objects_per_frame=2)
    with pytest.raises(SystemExit, match="no crop stage"):
        crop_stage_ablation.main([str(detector_checkpoint(tmp_path / "plain.pt", 0)), str(root), "--split", "all"])


def test_the_second_pass_drops_the_stage_and_both_keep_the_protocol_asked(tmp_path, monkeypatch, detector_checkpoint):
    import omnigen.detector.predict as predict

    root = tmp_path / "ds"
    write_fake_dataset(root, n_frames=2, objects_per_frame=2)
    calls, real = [], predict.predict_split

    def spy(model, state, *a, **kw):
        calls.append((model.crop_net is not None, kw["multi_label"]))
        return real(model, state, *a, **kw)

    monkeypatch.setattr(predict, "predict_split", spy)
    argv = [str(detector_checkpoint(tmp_path / "crop.pt", 16)), str(root), "--split", "all", "--imgsz", "64", "--device", "cpu"]
    assert crop_stage_ablation.main(argv) == 0
    assert calls == [(True, True), (False, True)]  # with the stage, then the head's corners
    calls.clear()
    assert crop_stage_ablation.main([*argv, "--single-label"]) == 0
    assert calls == [(True, False), (False, False)]


def test_a_class_naming_stage_is_also_scored_with_the_heads_scores(tmp_path, capsys, monkeypatch, detector_checkpoint):
    """Five passes for a stage that names classes: rescored, the crop's corners with the head's
    scores, rescored by the anchor's best score (alone and with every class), and the head alone; the boxes are the same each time, whatever order the rescoring sorts them in."""
    import omnigen.detector.predict as predict

    root = tmp_path / "ds"
    write_fake_dataset(root, n_frames=2, objects_per_frame=3)
    calls, real = [], predict.predict_split

    def spy(model, state, *a, **kw):
        calls.append((model.crop_net is not None, kw.get("crop_classes", True), kw.get("crop_score_by", "class")))
        return real(model, state, *a, **kw)

    monkeypatch.setattr(predict, "predict_split", spy)
    out = tmp_path / "ablation.json"
    argv = [str(detector_checkpoint(tmp_path / "crop.pt", 16, crop_classes=True)), str(root), "--split", "all", "--imgsz", "64",
            "--device", "cpu", "--out", str(out), "--by-class"]
    assert crop_stage_ablation.main(argv) == 0
    assert calls == [(True, True, "class"), (True, False, "class"), (True, True, "object"), (True, True, "every"),
                     (False, True, "class")]
    printed = capsys.readouterr().out.strip().splitlines()
    assert "rescored by the crop's classes: mAP50:95 " in printed[-1] and "scored by every " in printed[-1]
    assert any(line.startswith("| synthetic | crop stage, head's scores |") for line in printed)
    assert any(line.startswith("| synthetic | crop stage, scored by every |") for line in printed)
    result = json.loads(out.read_text())
    assert (result["crop_stage_head_scores"].keys() == result["crop_stage"].keys()
            == result["crop_stage_scored_by_object"].keys() == result["crop_stage_scored_by_every"].keys())
    assert any(k.startswith("class=") for k in result["crop_stage"])  # --by-class
    assert any(line.startswith("| class=") for line in printed)
    assert crop_stage_ablation.main([*argv, "--single-label"]) == 0  # relabelling passes are not refused


def test_same_boxes_ignores_order_and_scores_but_not_boxes():
    a = [{"image_id": 1, "category_id": 1, "bbox": [0, 0, 2, 2], "score": 0.9},
         {"image_id": 1, "category_id": 2, "bbox": [0, 0, 2, 2], "score": 0.5}]
    b = [dict(a[1], score=0.7), dict(a[0], score=0.1)]
    assert crop_stage_ablation.same_boxes(a, b)
    assert not crop_stage_ablation.same_boxes(a, [a[0], dict(a[1], bbox=[0, 0, 2, 3])])
