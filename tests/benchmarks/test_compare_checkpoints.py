"""benchmarks/compare_checkpoints.py: checkpoints scored side by side, on a tiny fake dataset (the
figures are meaningless; the plumbing is what is checked)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks import compare_checkpoints  # noqa: E402
from omnigen.fakes import write_fake_dataset  # noqa: E402


def test_scores_each_checkpoint_on_the_same_split_and_writes_the_rows(tmp_path, capsys, detector_checkpoint):
    root = tmp_path / "ds"
    write_fake_dataset(root, n_frames=3, objects_per_frame=3)
    a = detector_checkpoint(tmp_path / "a.pt", 16, crop_classes=True)
    b = detector_checkpoint(tmp_path / "b.pt", 0)
    out = tmp_path / "rows.json"
    argv = [str(root), str(a), str(b), "--split", "all", "--imgsz", "64", "--device", "cpu", "--out", str(out)]
    assert compare_checkpoints.main(argv) == 0
    printed = capsys.readouterr().out.strip().splitlines()
    assert printed[-1].startswith(f"compare_checkpoints: {b} mAP50:95 ") and f"({a} " in printed[-1]
    assert any(line.startswith(f"| synthetic | {a} |") for line in printed)
    assert any(line.startswith(f"| synthetic | {b} |") for line in printed)
    rows = json.loads(out.read_text())["rows"]
    assert set(rows) == {str(a), str(b)} and rows[str(a)].keys() == rows[str(b)].keys()


def test_a_checkpoint_named_twice_is_refused(tmp_path, detector_checkpoint):
    root = tmp_path / "ds"
    write_fake_dataset(root, n_frames=1, objects_per_frame=2)
    a = str(detector_checkpoint(tmp_path / "a.pt", 0))
    with pytest.raises(SystemExit, match="named twice"):
        compare_checkpoints.main([str(root), a, a, "--split", "all"])
