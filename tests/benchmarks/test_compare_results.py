"""benchmarks/compare_results.py: two validate runs' results.json side by side."""

from __future__ import annotations

import json

import pytest

from benchmarks import compare_results


def _results(map_, classes, adherence=5.0):
    rows = [{"group": f"class={name}", "objects": n, "oks_map50_95": m, "ap_oks50": 2 * m, "recall": 0.5}
            for name, n, m in classes]
    return {"oks_map50_95": map_, "ap_oks50": 2 * map_, "precision": 0.4, "recall": 0.3, "f1": 0.34,
            "corner_error_px": 5.0, "corner_error_rel": 0.2, "baseline": {"corner_error_rel": 0.5},
            "runs": [{"synthetic_test": {"ground_adherence_deg": adherence}}],
            "by_view": [{"group": "view=aerial", "objects": 10, "oks_map50_95": map_, "ap_oks50": 0.1, "recall": 0.2}],
            "by_class": rows}


def test_prints_both_runs_rows_their_changes_and_counts_the_classes_that_moved(tmp_path, capsys):
    old = _results(0.030, [("car", 100, 0.20), ("tram", 5, 0.00), ("bus", 9, 0.05)])
    new = _results(0.045, [("car", 100, 0.19), ("tram", 5, 0.04), ("bus", 9, 0.05), ("barrow", 2, 0.01)], adherence=4.0)
    (tmp_path / "a.json").write_text(json.dumps(old))
    (tmp_path / "b.json").write_text(json.dumps(new))
    assert compare_results.main([str(tmp_path / "a.json"), str(tmp_path / "b.json"), "--labels", "before", "after"]) == 0
    out = capsys.readouterr().out
    assert "| OKS mAP50:95 | 0.030 | 0.045 | +0.015 |" in out
    assert "| adherence (deg) | 5.00 | 4.00 | -1.00 |" in out
    assert "| car | 100 | 0.200 | 0.190 | -0.010 |" in out and "| bus | 9 | 0.050 | 0.050 | 0.000 |" in out
    assert "| barrow | 2 | - | 0.010 | - |" in out  # a class only the later run has
    assert out.strip().splitlines()[-1] == \
        "compare: mAP50:95 0.030 -> 0.045 (target 0.10); classes better 1, worse 1, of 3"


def test_refuses_a_file_that_is_not_a_validate_results_file_naming_it_and_the_field(tmp_path):
    (tmp_path / "a.json").write_text(json.dumps({"oks_map50_95": 0.1}))
    (tmp_path / "b.json").write_text("{not json")
    with pytest.raises(SystemExit, match=r"a\.json: no field 'by_view'"):
        compare_results.main([str(tmp_path / "a.json"), str(tmp_path / "a.json")])
    with pytest.raises(SystemExit, match=r"b\.json: not a readable JSON file"):
        compare_results.main([str(tmp_path / "b.json"), str(tmp_path / "a.json")])
