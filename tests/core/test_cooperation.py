"""Cross-frame checks of sequences (omnigen.cooperation) and their use by `omnigen validate`, on
fake cooperative records whose views agree by construction (fakes.fake_cooperative_records)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from omnigen.checks import check_dataset
from omnigen.cooperation import disagreements, jumps, shared_by_view_pair, world_boxes
from omnigen.fakes import fake_cooperative_records, random_frame, write_cooperative_dataset
from omnigen.geometry import Box3D


def shifted(rec, track: int, offset) -> object:
    """`rec` with track `track`'s box moved by `offset` metres in its camera frame."""
    objects = [replace(o, box=Box3D(o.box.center + np.asarray(offset), o.box.dims, o.box.rotation))
               if o.track_id == track else o for o in rec.objects]
    return replace(rec, objects=objects)


@pytest.fixture(scope="module")
def records():
    return fake_cooperative_records(seed=3, n_sequences=2, n_instants=3)


def test_world_boxes_map_camera_boxes_by_the_pose(records):
    rec = records[0]
    boxes = world_boxes(rec)
    m = rec.camera_to_world
    for o, b in zip(rec.objects, boxes):
        np.testing.assert_allclose(b.center, m[:3, :3] @ o.box.center + m[:3, 3])
    assert world_boxes(replace(rec, camera_to_world=None)) is None


def test_consistent_views_neither_disagree_nor_jump(records):
    assert disagreements(records) == []
    assert jumps(records) == []


def test_a_2cm_disagreement_is_found_and_a_1mm_one_is_not(records):
    one = [shifted(records[1], 2, [0.02, 0, 0]) if i == 1 else r for i, r in enumerate(records)]
    found = disagreements(one)
    assert len(found) == 2  # the moved view against each of the two others
    assert all(d.track_id == 2 and records[1].frame_id in (d.frame_a, d.frame_b) for d in found)
    assert {d.frame_a for d in found} | {d.frame_b for d in found} == {r.frame_id for r in records[:3]}
    assert all(abs(d.distance - 0.02) < 1e-9 for d in found)
    tiny = [shifted(records[1], 2, [0.001, 0, 0]) if i == 1 else r for i, r in enumerate(records)]
    assert disagreements(tiny) == []


def test_a_jump_is_found_in_its_view_only(records):
    views = len({r.view for r in records})
    later = views  # the first view's frame at the second instant
    moved = [shifted(r, 1, [5.0, 0, 0]) if i == later else r for i, r in enumerate(records)]
    found = jumps(moved)
    assert {(j.track_id, j.view) for j in found} == {(1, records[later].view)}
    assert {(j.frame_a, j.frame_b) for j in found} == {(records[0].frame_id, records[later].frame_id),
                                                      (records[later].frame_id, records[2 * views].frame_id)}
    assert all(j.speed > 40 for j in found)


def test_shared_by_view_pair_counts_tracks_both_views_saw(records):
    first = records[:3]  # one instant, three views
    fewer = [replace(first[0], objects=first[0].objects[:2]), *first[1:]]
    shared = shared_by_view_pair(fewer)
    a, b, c = sorted(r.view for r in first)
    n = len(first[1].objects)
    ego_pairs = [k for k in shared if first[0].view in k]
    assert all(shared[k] == [2] for k in ego_pairs)
    assert [shared[k] for k in shared if first[0].view not in k] == [[n]]
    assert len(shared) == 3 and (a, b) in shared and (b, c) in shared


def test_frames_without_sequence_or_pose_are_left_out():
    legacy = random_frame(0, 0)
    assert disagreements([legacy, legacy]) == [] and shared_by_view_pair([legacy]) == {}


def test_validate_reports_a_disagreement_and_a_jump_naming_frames_and_track(tmp_path, records):
    views = len({r.view for r in records})
    bad = [shifted(r, 2, [0.05, 0, 0]) if i == 1 else r for i, r in enumerate(records)]
    bad[views] = shifted(bad[views], 1, [0, 0, 5.0])  # the first view, second instant: apart and jumping
    write_cooperative_dataset(tmp_path / "d", bad)
    _, problems = check_dataset(tmp_path / "d", show_progress=False)
    lines = [str(p) for p in problems if p.field == "objects.track_id"]
    apart = [line for line in lines if "apart" in line]
    fast = [line for line in lines if "m/s" in line]
    assert sorted(line.split("track ")[1][0] for line in apart) == ["1", "1", "2", "2"]
    assert all(records[1].frame_id in line for line in apart if "track 2" in line)
    assert fast and all("track 1" in line and records[views].frame_id in line for line in fast)
    assert len(lines) == len(problems)


def test_validate_passes_consistent_sequences(tmp_path):
    write_cooperative_dataset(tmp_path / "d", seed=1, n_sequences=1, n_instants=2)
    n, problems = check_dataset(tmp_path / "d", show_progress=False)
    assert n == 6 and problems == []
