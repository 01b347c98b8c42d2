"""Issue 25: the fixed-budget learning benchmark runs end to end and prints the model beside the
box-template baseline (tiny model, a few steps on a fake dataset with train and test splits)."""

from __future__ import annotations

import json

import pytest

pytest.importorskip("cv2", reason="opencv-python-headless is part of the train extra")

from benchmarks.bench_learning import main  # noqa: E402
from omnigen.fakes import write_fake_dataset  # noqa: E402
from omnigen.splits import write_split  # noqa: E402


def test_bench_learning_prints_model_and_baseline(tmp_path, capsys):
    ds = write_fake_dataset(tmp_path / "uov", 9, objects_per_frame=4, seed=5)
    ids = [ds.table.frame_id[i] for i in range(len(ds))]
    write_split(ds.root, "train", ids[:6])
    write_split(ds.root, "test", ids[6:])
    out = tmp_path / "result.json"
    argv = [str(ds.root), "--steps", "2", "--batch", "3", "--imgsz", "64", "--crop", "0", "--amp", "off",
            "--width", "0.125", "--depth", "0.34", "--workers", "0", "--kpt-mode", "box", "--kpt-l1", "1",
            "--kpt-turn", "--kpt-hidden", "16",
            "--work", str(tmp_path / "runs"), "--out", str(out)]
    assert main(argv) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[-1].startswith("learning: mAP50:95 ") and "(baseline " in lines[-1]
    assert "corner error rel" in lines[-1]
    result = json.loads(out.read_text())
    assert result["steps"] == 2 and result["config"]["kpt_mode"] == "box" and result["config"]["kpt_l1"] == 1.0
    assert result["config"]["kpt_turn"] is True and result["config"]["kpt_hidden"] == 16
    assert "turn" in result["final_losses"] and any(line.startswith("box-matched objects (") for line in lines)
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
        main(argv + ["--lr0", "0.01", "--name", result["name"]])
    assert (tmp_path / "runs" / result["name"] / "last.pt").read_bytes() == before


def test_turn_targets_reads_a_turn_aware_checkpoint(tmp_path, capsys):
    """benchmarks/turn_targets.py prints the share of turned targets of a turn-aware run and
    refuses a model without the turn."""
    from benchmarks.turn_targets import main as turn_main

    ds = write_fake_dataset(tmp_path / "uov", 6, objects_per_frame=4, seed=3)
    ids = [ds.table.frame_id[i] for i in range(len(ds))]
    write_split(ds.root, "train", ids[:4])
    write_split(ds.root, "test", ids[4:])
    common = [str(ds.root), "--steps", "1", "--batch", "2", "--imgsz", "64", "--crop", "0", "--amp", "off",
              "--width", "0.125", "--depth", "0.34", "--workers", "0", "--kpt-mode", "box",
              "--work", str(tmp_path / "runs")]
    assert main([*common, "--kpt-turn", "--name", "turn"]) == 0
    capsys.readouterr()
    assert turn_main([str(tmp_path / "runs" / "turn" / "last.pt"), "--batches", "2", "--batch", "2"]) == 0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    share = float(last.split("turned ")[1].split(" ")[0])
    assert last.startswith("turn targets: turned ") and 0.0 <= share <= 1.0 and "turn loss" in last
    assert main([*common, "--name", "plain"]) == 0
    with pytest.raises(SystemExit, match="not a turn-aware model"):
        turn_main([str(tmp_path / "runs" / "plain" / "last.pt")])
