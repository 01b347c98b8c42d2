"""benchmarks/common.py floor_rows (bench_adherence_floor.py, validate.py): the truth handed to the evaluation scores as the truth should."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks.common import floor_rows, truth_as_predictions  # noqa: E402
from omnigen.fakes import write_fake_dataset  # noqa: E402
from omnigen.taxonomy import recorded_taxonomy  # noqa: E402


def test_exact_corners_score_full_marks_and_noise_costs(tmp_path):
    ds = write_fake_dataset(tmp_path / "fake", 6, objects_per_frame=6, seed=4, images=False)
    exact = truth_as_predictions(ds, None, 0.0, np.random.default_rng(0), recorded_taxonomy(ds.manifest))
    assert exact and all(p["score"] == 1.0 and len(p["keypoints"]) == 24 for p in exact)
    for p in exact:  # each prediction is exactly one of its frame's objects
        i = ds.index_of(p["frame_id"])
        own = ds.objects.keypoints[int(ds.offsets[i]):int(ds.offsets[i + 1])]
        assert np.isclose(own, np.asarray(p["keypoints"]).reshape(8, 3)[:, :2]).all(axis=(1, 2)).any()

    rows = {(r["noise_px"], r["group"]): r for r in floor_rows(ds, None, [0.0, 3.0], seed=0)}
    clean, noisy = rows[(0.0, "source=synthetic")], rows[(3.0, "source=synthetic")]
    assert clean["oks_map50_95"] > 0.95
    assert noisy["oks_map50_95"] < clean["oks_map50_95"] - 0.05
    assert math.isfinite(clean["adherence_deg"]) and clean["adherence_objects"] > 0
    assert noisy["adherence_deg"] > clean["adherence_deg"]
    again = {(r["noise_px"], r["group"]): r for r in floor_rows(ds, None, [0.0, 3.0], seed=0)}
    assert again == rows  # seeded: a rerun prints the same table
