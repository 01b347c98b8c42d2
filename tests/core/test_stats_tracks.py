"""stats.json's `tracks` section, on fake cooperative sequences whose tracks, speeds and shared
objects are known by construction; absent for a dataset without sequences."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from omnigen.cli import main
from omnigen.fakes import COOPERATIVE_FPS, fake_cooperative_records, write_cooperative_dataset, write_fake_dataset
from omnigen.geometry import Box3D
from omnigen.stats.tracks import tracks_section

N_SEQ, N_INSTANTS, N_OBJECTS = 2, 3, 4


@pytest.fixture(scope="module")
def records():
    return fake_cooperative_records(seed=6, n_sequences=N_SEQ, n_instants=N_INSTANTS, n_objects=N_OBJECTS)


def _report(tmp_path, root) -> dict:
    assert main(["stats", str(root), "--out", str(tmp_path / "r"), "--gallery", "0", "--no-check-images",
                 "--jobs", "1"]) == 0
    return json.loads((tmp_path / "r" / "stats.json").read_text())


def test_stats_json_has_tracks_for_sequences(tmp_path, records):
    stats = _report(tmp_path, write_cooperative_dataset(tmp_path / "coop", records).root)
    tracks = stats["tracks"]
    assert (tracks["sequences"], tracks["tracks"]) == (N_SEQ, N_SEQ * N_OBJECTS)
    assert tracks["instants_per_track"]["min"] == tracks["instants_per_track"]["max"] == N_INSTANTS
    assert tracks["seconds_per_track"]["max"] == pytest.approx((N_INSTANTS - 1) / COOPERATIVE_FPS)
    assert set(tracks["shared_by_view_pair"]) == {"aerial+ego", "aerial+infrastructure", "ego+infrastructure"}
    both = tracks["shared_by_view_pair"]["ego+infrastructure"]
    assert both == {"instants": N_SEQ * N_INSTANTS, "mean": N_OBJECTS, "total": N_SEQ * N_INSTANTS * N_OBJECTS}
    assert (tracks["disagreements"], tracks["jumps"]) == (0, 0)


def test_speeds_by_class_come_from_the_velocities(tmp_path, records):
    ds = write_cooperative_dataset(tmp_path / "coop", records)
    speeds = {}
    for r in records:
        for o in r.objects:
            speeds.setdefault(o.category, []).append(float(np.linalg.norm(o.velocity)))
    got = tracks_section(ds)["speed_by_class"]
    assert set(got) == set(speeds)
    for c, v in speeds.items():
        assert got[c]["n"] == len(v) and got[c]["median"] == pytest.approx(np.median(v), rel=1e-5)


def test_tracks_count_what_views_miss_and_where_they_disagree(tmp_path, records):
    """The ego view loses track 1 at the first instant (a view pair shares one object less there),
    and the next view places track 2 5 cm off (it disagrees with both other views)."""
    first, second = records[0], records[1]
    moved = [replace(o, box=Box3D(o.box.center + [0.05, 0, 0], o.box.dims, o.box.rotation)) if o.track_id == 2 else o
             for o in second.objects]
    edited = [replace(first, objects=[o for o in first.objects if o.track_id != 1]),
              replace(second, objects=moved), *records[2:]]
    tracks = tracks_section(write_cooperative_dataset(tmp_path / "coop", edited))
    ego_infra = tracks["shared_by_view_pair"]["ego+infrastructure"]
    assert ego_infra["total"] == N_SEQ * N_INSTANTS * N_OBJECTS - 1
    assert (tracks["disagreements"], tracks["jumps"]) == (2, 0)


def test_stats_json_has_no_tracks_without_sequences(tmp_path):
    stats = _report(tmp_path, write_fake_dataset(tmp_path / "ds", 4, objects_per_frame=3, source="kitti").root)
    assert "tracks" not in stats
