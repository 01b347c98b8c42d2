"""benchmarks/validate.py's resume rules: what a done-marker means and which records a redo drops."""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.validate import Runner, mentions, stale  # noqa: E402


def test_mentions_names_a_folder_and_its_files_not_its_siblings():
    run = Path("runs/v/runs/n-p2")
    assert mentions("omnigen train uov --out runs/v/runs/n-p2 --epochs 60", run)
    assert mentions("omnigen eval runs/v/runs/n-p2/test-predictions.json uov", run)
    assert mentions("predict_dataset(runs/v/runs/n-p2, uov)", run)
    assert mentions("omnigen train uov --out runs/v/runs/n-p2", run)
    assert not mentions("omnigen train uov --out runs/v/runs/n-p2-480 --epochs 60", run)
    assert not mentions("omnigen train uov --out runs/v/runs/n-p2x", run)


def test_a_marker_from_other_arguments_is_stale(tmp_path):
    marker = tmp_path / "done"
    assert not stale(marker, "train --epochs 60")  # no marker: nothing to redo, nothing done
    marker.write_text("train --epochs 30\n")
    assert stale(marker, "train --epochs 60")
    marker.write_text("train --epochs 60\n")
    assert not stale(marker, "train --epochs 60")


def test_forget_drops_only_the_redone_folder(tmp_path):
    run = Runner(tmp_path)
    run.record("omnigen train uov --out w/runs/n-p2 --epochs 30", 10.0)
    run.record("omnigen train uov --out w/runs/n-p2-480 --epochs 30", 20.0)
    run.record("omnigen eval w/runs/n-p2/test-predictions.json uov", 1.0)
    run.forget(Path("w/runs/n-p2"))
    assert [c["command"] for c in run.log] == ["omnigen train uov --out w/runs/n-p2-480 --epochs 30"]
    assert Runner(tmp_path).log == run.log  # the log on disk says the same


def test_object_sizes_per_view_of_a_split(tmp_path):
    import numpy as np

    from benchmarks.validate import object_sizes
    from omnigen.fakes import write_fake_dataset
    from omnigen.splits import write_split

    ds = write_fake_dataset(tmp_path / "ds", n_frames=6, seed=3)
    test = ds.frame_ids[:3]
    write_split(ds.root, "test", test)
    sizes = object_sizes(ds.root, "test")
    rows = [ds.index_of(f) for f in test]
    o = ds.objects
    keep = np.isin(o.frame, rows)
    assert sum(v["objects"] for v in sizes.values()) == int(keep.sum())
    for view, v in sizes.items():
        assert v["p10_px"] <= v["p50_px"] <= v["p90_px"]
