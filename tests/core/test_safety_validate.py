"""Issue 44, hole 2 (validate's part): `omnigen validate` applies the plausibility bounds to every
record, whoever wrote it, not only the converters to what they read."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import pytest

from omnigen.checks import check_dataset
from omnigen.cli import main as cli
from omnigen.dataset import MANIFEST, record_files
from omnigen.fakes import random_frame, write_fake_dataset
from omnigen.geometry import Box3D
from omnigen.plausible import (MAX_KEYPOINT_COORDINATE, MAX_PIXEL_COORDINATE, record_problems,
                               worst_keypoint_coordinate)
from omnigen.record import FrameRecord, ObjectRecord
from omnigen.writer import update_records_digest


def reseal(root: Path) -> None:
    """What a hand edit followed by a re-seal leaves: the manifest's records_sha256 matches again,
    so only the records' own values can tell."""
    digest = hashlib.sha256()
    for e in record_files(root):
        update_records_digest(digest, e.name, Path(e.path).read_bytes())
    manifest = json.loads((root / MANIFEST).read_text())
    manifest["records_sha256"] = digest.hexdigest()
    (root / MANIFEST).write_text(json.dumps(manifest))


def edit_record(root: Path, index: int, edit) -> Path:
    path = Path(record_files(root)[index].path)
    d = json.loads(path.read_text())
    edit(d)
    path.write_text(json.dumps(d))
    return path


@pytest.fixture
def dataset(tmp_path: Path) -> Path:
    return write_fake_dataset(tmp_path / "ds", n_frames=4, objects_per_frame=3, seed=3, source="kitti").root


def _absurd(d: dict) -> None:
    o = d["objects"][0]
    o["box3d"]["center"] = [1e308, -1e308, 1e308]
    o["box3d"]["dims"] = [1e308, 2.0, 1.5]
    o["keypoints"] = [None if k is None else [1e308, -1e308] for k in o["keypoints"]]
    o["bbox"] = [-1e308, -1e308, 1e308, 1e308]
    d["ignore_regions"] = [{"bbox": [0.0, 0.0, 1e308, 1e308], "label": "DontCare"}]
    d["K"][0][0] = 1e300


def test_absurd_finite_values_in_a_resealed_dataset_are_problems_naming_file_and_field(dataset, capsys):
    path = edit_record(dataset, 1, _absurd)
    reseal(dataset)
    n, problems = check_dataset(dataset, show_progress=False)
    fields = {p.field for p in problems}
    assert n == 4 and all(p.file == str(path) for p in problems)
    assert {"K", "objects[0].box3d.center", "objects[0].box3d.dims", "objects[0].bbox",
            "ignore_regions[0].bbox"} <= fields
    assert any(f.startswith("objects[0].keypoints[") for f in fields)
    assert any("MAX_OBJECT_DISTANCE_M" in p.message for p in problems)
    assert cli(["validate", str(dataset)]) == 1
    out = capsys.readouterr().out
    assert f"{path}: objects[0].box3d.center: location [1e+308, -1e+308, 1e+308] lies beyond 1000 m" in out
    assert "INVALID" in out


def test_tiny_boxes_far_cameras_and_far_2d_boxes_are_problems(dataset):
    def edit(d: dict) -> None:
        d["objects"][1]["box3d"]["dims"] = [1e-9, 1.0, 1.0]
        d["objects"][2]["bbox_source"] = [0.0, 0.0, 2e5, 10.0]
        d["camera_height"] = 5e4
        d["ground_plane"]["offset"] = 5e4
    path = edit_record(dataset, 0, edit)
    reseal(dataset)
    problems = {(p.file, p.field) for p in check_dataset(dataset, show_progress=False)[1]}
    assert problems == {(str(path), f) for f in ("objects[1].box3d.dims", "objects[2].bbox_source",
                                                 "camera_height", "ground_plane.offset")}


def test_a_real_object_straddling_the_image_plane_is_plausible():
    """A bus passing a 1920-pixel camera, its rear corners 0.12 m ahead and 6 m to the side: they
    project a hundred thousand pixels out, beyond MAX_PIXEL_COORDINATE, and are real data."""
    K = np.array([[2000.0, 0, 960], [0, 2000.0, 540], [0, 0, 1]])
    along_the_optical_axis = np.array([[0.0, -1, 0], [0, 0, -1], [1, 0, 0]])
    box = Box3D([5.0, 0.5, 6.12], [12.0, 2.5, 3.2], along_the_optical_axis)
    obj = ObjectRecord.from_box("bus", 1, box, K, 1920, 1080)
    assert obj is not None and np.nanmax(np.abs(obj.keypoints)) > MAX_PIXEL_COORDINATE
    rec = FrameRecord("kitti-x", "kitti", "ego", "images/x.png", 1920, 1080, K, [obj])
    FrameRecord.from_dict(rec.to_dict())
    assert record_problems(rec) == []


def test_far_camera_positions_and_fast_objects_are_problems():
    """camera_to_world may sit in a map projection (millions of metres) but not beyond
    MAX_WORLD_COORDINATE_M; an object may move fast, not beyond MAX_SPEED_M_S."""
    rec = random_frame(seed=5, index=2, n_objects=4, sequence=True)
    rec.camera_to_world[:3, 3] = [3.39e6, 2.09e6, 20.0]  # DAIR-V2X-C's world: plausible
    rec.objects[1].velocity = np.array([60.0, 0.0, 0.0])
    assert record_problems(rec) == []
    rec.camera_to_world[1, 3] = -2e7
    rec.objects[1].velocity = np.array([60.0, 40.0, 0.0])
    problems = record_problems(rec)
    assert [field for field, _ in problems] == ["camera_to_world", "objects[1].velocity"]
    assert "MAX_WORLD_COORDINATE_M" in problems[0][1]
    assert "exceeds 70 m/s (MAX_SPEED_M_S)" in problems[1][1]


def test_the_keypoint_bound_lies_beyond_what_any_record_within_the_other_bounds_projects():
    assert worst_keypoint_coordinate() < MAX_KEYPOINT_COORDINATE
    assert MAX_KEYPOINT_COORDINATE**2 < np.finfo(np.float32).max  # squared distances stay finite


def test_fake_datasets_pass_the_bounds(tmp_path):
    for source in ("synthetic", "kitti", "dair-v2x-i"):
        root = write_fake_dataset(tmp_path / source, n_frames=12, objects_per_frame=8, seed=9, source=source,
                                  sequence=source == "kitti").root
        assert check_dataset(root, show_progress=False)[1] == []


def test_max_problems_is_checked_when_parsed(dataset, capsys):
    with pytest.raises(SystemExit) as exc:
        cli(["validate", str(dataset), "--max-problems", "-1"])
    assert exc.value.code == 2 and "-1 is outside [0, inf)" in capsys.readouterr().err
