"""Issue 25: the fixed-budget learning benchmark runs end to end and prints the model beside the
box-template baseline (tiny model, a few steps on a fake dataset with train and test splits)."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("cv2", reason="opencv-python-headless is part of the train extra")

from benchmarks.bench_learning import main  # noqa: E402
from omnigen.detector.model.checkpoint import load_checkpoint  # noqa: E402
from omnigen.fakes import write_fake_dataset  # noqa: E402
from omnigen.splits import write_split  # noqa: E402


def test_bench_learning_prints_model_and_baseline(tmp_path, capsys):
    ds = write_fake_dataset(tmp_path / "uov", 9, objects_per_frame=4, seed=5)
    ids = [ds.table.frame_id[i] for i in range(len(ds))]
    write_split(ds.root, "train", ids[:6])
    write_split(ds.root, "test", ids[6:])
    out = tmp_path / "result.json"
    argv = [str(ds.root), "optim.batch=3", "model.imgsz=64", "data.window=0", "data.repeat_thresh=0",
            "loss.kpt_l1=1", "crop_stage.steps=2", "crop_stage.batch=4", "crop_stage.copies=1",
            "--steps", "2", "--amp", "off", "--width", "0.125", "--depth", "0.34", "--workers", "0",
            "--work", str(tmp_path / "runs"), "--out", str(out)]
    assert main(argv) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[-1].startswith("learning: mAP50:95 ") and "(baseline " in lines[-1]
    assert "corner error rel" in lines[-1]
    result = json.loads(out.read_text())
    # the recipe (make validate's) with the keys given: its crop phase too
    assert result["steps"] == 2 and result["config"]["kpt_mode"] == "box" and result["config"]["kpt_l1"] == 1.0
    assert result["config"]["kpt_heading"] is True and result["config"]["crop_phase"]["steps"] == 2
    assert load_checkpoint(tmp_path / "runs" / result["name"] / "last.pt")["crop_stage"]["steps_done"] == 2
    assert "heading" in result["final_losses"] and any(line.startswith("box-matched objects (") for line in lines)
    assert set(result["corner_order"]) >= {"matched", "as labelled", "turned 180"}
    assert set(result["model"]) == set(result["baseline"]) and "synthetic" in result["model"]
    for row in (*result["model"].values(), *result["baseline"].values()):
        assert {"oks_map50_95", "ap_oks50", "corner_error_px", "corner_error_rel"} <= set(row)
    assert (tmp_path / "runs" / result["name"] / "last.pt").exists()

    # a rerun of the same recipe scores the finished run again instead of training it anew
    assert main(argv) == 0
    again = capsys.readouterr().out
    assert "trained before with these arguments" in again and again.strip().splitlines()[-1] == lines[-1]
    assert json.loads(out.read_text())["model"] == result["model"]

    # another recipe into the same folder is refused, the finished run left as it was
    before = (tmp_path / "runs" / result["name"] / "last.pt").read_bytes()
    with pytest.raises(SystemExit, match="other arguments.*lr0"):
        main([*argv[:1], "optim.lr0=0.01", *argv[1:], "--name", result["name"]])
    assert (tmp_path / "runs" / result["name"] / "last.pt").read_bytes() == before
