"""`omnigen export kitti-tracking`: one KITTI tracking sequence per (sequence, view), frames by
timestamp, on fake cooperative sequences."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from omnigen.cli import main
from omnigen.converters.kitti_tracking_export import export_kitti_tracking
from omnigen.fakes import fake_cooperative_records, write_cooperative_dataset
from omnigen.formats.kitti import label_line

N_INSTANTS = 3


@pytest.fixture
def records():
    """Two sequences of three views; timestamps run against frame-id order (numbering must follow
    time), and two frames of the first instant lose their sequence (skipped)."""
    recs = fake_cooperative_records(seed=8, n_sequences=2, n_instants=N_INSTANTS, n_objects=3)
    recs = [replace(r, timestamp=round((N_INSTANTS - 1) / 10 - r.timestamp, 6)) for r in recs]
    for i in (0, 3 * N_INSTANTS):
        recs[i] = replace(recs[i], sequence=None, timestamp=None)
    return recs


def test_sequences_labels_calib_pose_and_images(tmp_path, records):
    ds = write_cooperative_dataset(tmp_path / "coop", records)
    report = export_kitti_tracking(ds, tmp_path / "kt")
    out = tmp_path / "kt"
    mapping = (out / "mapping.txt").read_text().splitlines()
    expected = sorted({(r.sequence, r.view) for r in records if r.sequence})
    assert mapping == [f"{s:04d} {seq} {view}" for s, (seq, view) in enumerate(expected)]
    assert (report.sequences, report.frames, report.skipped) == (6, 16, 2)
    for s, (seq, view) in enumerate(expected):
        frames = sorted((r for r in records if (r.sequence, r.view) == (seq, view)), key=lambda r: r.timestamp)
        lines = (out / "label_02" / f"{s:04d}.txt").read_text().splitlines()
        want = [f"{n} {o.track_id} {label_line(r, o)}" for n, r in enumerate(frames) for o in r.objects]
        assert lines == want
        assert sorted(p.name for p in (out / "image_02" / f"{s:04d}").iterdir()) == [
            f"{n:06d}.png" for n in range(len(frames))]
        assert (out / "image_02" / f"{s:04d}" / "000000.png").read_bytes() == (ds.root / frames[0].image).read_bytes()
        poses = np.loadtxt(out / "pose" / f"{s:04d}.txt", ndmin=2).reshape(-1, 3, 4)
        np.testing.assert_array_equal(poses, [r.camera_to_world[:3] for r in frames])
        assert (out / "calib" / f"{s:04d}.txt").read_text().startswith("P0: ")


def test_a_k_that_changes_within_a_sequence_is_refused_naming_the_frame(tmp_path, records):
    later = next(i for i, r in enumerate(records) if r.sequence and r.view == "aerial" and i > 3)
    K = records[later].K.copy()
    K[0, 0] += 1.0
    records[later] = replace(records[later], K=K)
    ds = write_cooperative_dataset(tmp_path / "coop", records)
    with pytest.raises(ValueError, match=rf"{records[later].frame_id}\.json: K: differs"):
        export_kitti_tracking(ds, tmp_path / "kt")
    assert not (tmp_path / "kt").exists() or not any((tmp_path / "kt").iterdir())


def test_cli_export_kitti_tracking(tmp_path, records, capsys):
    write_cooperative_dataset(tmp_path / "coop", records)
    args = ["export", "kitti-tracking", str(tmp_path / "coop"), "--out", str(tmp_path / "kt"), "--link", "copy"]
    assert main(args) == 0
    assert "2 frames without a sequence were skipped" in capsys.readouterr().out
    assert main(args) == 0  # a rerun replaces its own export
    assert len((tmp_path / "kt" / "mapping.txt").read_text().splitlines()) == 6
