"""benchmarks/vertical_snap.py: the true point it scores against, its error measure, and the
snap of each image's predictions, on a fake dataset's own corners."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks import vertical_snap as vs  # noqa: E402
from benchmarks.bench_adherence_floor import truth_as_predictions  # noqa: E402
from omnigen.fakes import write_fake_dataset  # noqa: E402
from omnigen.taxonomy import recorded_taxonomy  # noqa: E402


def test_the_error_measure_is_zero_for_the_same_point_and_grows_with_the_miss():
    v = np.array([0.1, 0.9, 0.4])
    v /= np.linalg.norm(v)
    assert vs.point_error_deg(v, v) == pytest.approx(0.0, abs=1e-6)
    assert vs.point_error_deg(-v, v) == pytest.approx(0.0, abs=1e-6)  # a line's direction, not its sense
    near, far = np.array([0.12, 0.9, 0.4]), np.array([0.4, 0.9, 0.4])
    assert 0 < vs.point_error_deg(near / np.linalg.norm(near), v) < vs.point_error_deg(far / np.linalg.norm(far), v)


def test_variants_name_snap_options_and_bad_ones_exit_naming_the_key():
    name, opts = vs.parse_variant("wide:gate_deg=40,candidates=10")
    assert name == "wide" and opts.gate_deg == 40.0 and opts.candidates == 10
    with pytest.raises(SystemExit, match="'gates' is not one of"):
        vs.parse_variant("x:gates=4")
    with pytest.raises(SystemExit, match="not a number"):
        vs.parse_variant("x:gate_deg=wide")


def test_the_truths_own_corners_give_the_true_point_and_snap_to_themselves(tmp_path):
    ds = write_fake_dataset(tmp_path / "fake", 6, objects_per_frame=6, seed=4, images=False)
    preds = [p | {"image_id": ds.index_of(p["frame_id"]) + 1}  # as prediction numbers them
             for p in truth_as_predictions(ds, None, 0.0, np.random.default_rng(0), recorded_taxonomy(ds.manifest))]

    def blank(image_id: int) -> np.ndarray:  # no line segments: the detections' point stands
        f = image_id - 1
        return np.full((int(ds.table.height[f]), int(ds.table.width[f])), 128, np.uint8)

    out, points, seconds = vs.snapped(preds, blank, vs.parse_variant("default:")[1])
    assert points and len(seconds) == len(points)
    for image_id, (first, v) in points.items():
        f = image_id - 1
        truth = vs.true_point(ds.table.K[f], ds.table.ground_plane[f], float(ds.table.width[f]),
                              float(ds.table.height[f]))
        assert np.allclose(v, first) and vs.point_error_deg(v, truth) < 0.05
        assert np.dot(v, truth) > 0  # signed alike: towards the bottom faces
    for p, q in zip(preds, out):
        assert np.allclose(p["keypoints"], q["keypoints"], atol=1e-3)  # already aimed: unchanged
    adherence, mean_ap = vs.adherence_and_map(ds, out, [str(f) for f in ds.table.frame_id])
    assert mean_ap > 0.99 and adherence["overall"] < 1.5
