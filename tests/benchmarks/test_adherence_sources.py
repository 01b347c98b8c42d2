"""benchmarks/adherence_sources.py: the true vanishing point and the corner replacements do what
they say (the fit and the turn: tests/detector/test_vanishing.py), and the script's table holds
the figures its last line prints."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from benchmarks import adherence_sources as src  # noqa: E402
from benchmarks.bench_adherence_floor import truth_as_predictions  # noqa: E402
from omnigen.fakes import write_fake_dataset  # noqa: E402
from omnigen.taxonomy import recorded_taxonomy  # noqa: E402


def as_pixels(v: np.ndarray, width: float = 640.0, height: float = 480.0) -> np.ndarray:
    return v[:2] / v[2] * max(width, height) + np.array([(width - 1) / 2, (height - 1) / 2])


def test_the_true_vanishing_point_is_where_the_ground_normal_projects():
    K = np.array([[500.0, 0, 320], [0, 500, 240], [0, 0, 1]])
    n = np.array([0.0, -0.8, -0.6])  # a camera pitched down: up is -y and towards the camera
    v = src.true_vanishing_point(K, np.array([*n, 5.0]), 640, 480)
    far = K @ (np.array([1.0, 2.0, 20.0]) + 1e7 * n)
    assert np.allclose(as_pixels(v), far[:2] / far[2], atol=1e-3)


def test_the_face_and_offset_replacements_take_one_part_from_the_truth():
    rng = np.random.default_rng(2)
    pred, true = rng.normal(0, 10, (8, 2)), rng.normal(0, 10, (8, 2))
    faces = src.true_face_shapes(pred, true)
    for f in (src.TOP, src.BOTTOM):
        assert np.allclose(faces[f].mean(0), pred[f].mean(0))
        assert np.allclose(faces[f] - faces[f].mean(0), true[f] - true[f].mean(0))
    moved = src.true_vertical_offset(pred, true)
    assert np.allclose(moved[src.TOP], pred[src.TOP])
    assert np.allclose(moved[src.BOTTOM] - moved[src.BOTTOM].mean(0), pred[src.BOTTOM] - pred[src.BOTTOM].mean(0))
    assert np.allclose(moved[src.BOTTOM].mean(0) - moved[src.TOP].mean(0), true[src.BOTTOM].mean(0) - true[src.TOP].mean(0))


def test_the_script_measures_every_variant_and_the_truth_scores_best(tmp_path, capsys):
    ds = write_fake_dataset(tmp_path / "fake", 6, objects_per_frame=6, seed=4, images=False)
    tax = recorded_taxonomy(ds.manifest)
    exact = {name: r["overall"]["mean"] for name, r in src.adherence_table(
        ds, truth_as_predictions(ds, None, 0.0, np.random.default_rng(0), tax), None, 0.3).items()}
    for name in ("true corners", "true face shapes", "true vertical offset"):
        assert exact[name] == pytest.approx(exact["as predicted"])  # the truth with the truth's parts: itself
    noisy = tmp_path / "noisy.json"
    noisy.write_text(json.dumps(truth_as_predictions(ds, None, 3.0, np.random.default_rng(0), tax)))
    out = tmp_path / "sources.json"
    assert src.main([str(ds.root), str(noisy), "--split", "all", "--out", str(out)]) == 0
    table = json.loads(out.read_text())["adherence_deg"]
    assert set(table) == {"as predicted", *src.VANISHING, *src.PER_OBJECT}
    assert table["true corners"]["overall"]["mean"] < table["as predicted"]["overall"]["mean"]
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last.startswith(f"adherence_sources: as predicted {table['as predicted']['overall']['mean']:.2f} deg")
    with pytest.raises(SystemExit, match="none.json"):
        src.main([str(ds.root), str(tmp_path / "none.json")])
