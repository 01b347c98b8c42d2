"""`omnigen convert kitti` and `omnigen export kitti` (issue 3).

Real frames come from ../shared/realdata/kitti (skipped with a reason when absent); everything else
runs on generated KITTI-format trees (omnigen.converters.kitti_fixture).
"""

from __future__ import annotations

import json
import math
import os
import shutil
import zipfile
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from omnigen.converters import kitti
from omnigen.converters.common import PARALLEL_MIN_FRAMES, run_conversion
from omnigen.converters.kitti_fixture import write_kitti_tree, write_kitti_zips
from omnigen.cli import main
from omnigen.dataset import Dataset
from omnigen.formats.kitti import camera_offset_from_projection, kitti_alpha, kitti_file_names
from omnigen.geometry import self_occluded_corners

REALDATA = Path(__file__).parents[2].parent / "shared" / "realdata"
REAL_KITTI = REALDATA / "kitti"


@pytest.fixture(scope="module")
def real_kitti() -> Path:
    if not (REAL_KITTI / "training" / "label_2").is_dir():
        pytest.skip(f"real KITTI frames not found at {REAL_KITTI} (../shared/realdata beside the checkout)")
    return REAL_KITTI


@pytest.fixture(scope="module")
def tree(tmp_path_factory) -> Path:
    """A generated KITTI root with 12 training frames (read-only for tests: copy before changing)."""
    root = tmp_path_factory.mktemp("kitti-src")
    write_kitti_tree(root, 12, seed=3)
    return root


@pytest.fixture(scope="module")
def converted(tree, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("kitti-ds") / "ds"
    assert convert(tree, out) == 0
    return out


def convert(src: Path, out: Path, *extra: str) -> int:
    return main(["convert", "kitti", str(src), "--out", str(out), *extra])


def record_texts(ds: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((ds / "records").glob("*.json"))}


def assert_same(a, b, path: str = "", tol: float = 1e-6) -> None:
    """Every field equal; numbers within `tol`. Fails naming the first differing field."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), f"{path}: keys {sorted(a)} != {sorted(b)}"
        for k in a:
            assert_same(a[k], b[k], f"{path}.{k}", tol)
    elif isinstance(a, list):
        assert isinstance(b, list) and len(a) == len(b), f"{path}: lengths differ"
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{path}[{i}]", tol)
    elif isinstance(a, (int, float)) and not isinstance(a, bool):
        assert isinstance(b, (int, float)) and not isinstance(b, bool), f"{path}: {a!r} vs {b!r}"
        assert abs(a - b) <= tol, f"{path}: {a!r} vs {b!r}"
    else:
        assert a == b, f"{path}: {a!r} vs {b!r}"


def assert_same_datasets(a: Path, b: Path) -> None:
    ra, rb = record_texts(a), record_texts(b)
    assert ra.keys() == rb.keys()
    for name in ra:
        assert_same(json.loads(ra[name]), json.loads(rb[name]), name)


# ---------------------------------------------------------------------------------------------
# Real frames
# ---------------------------------------------------------------------------------------------


def test_real_frames(real_kitti, tmp_path):
    out = tmp_path / "ds"
    assert convert(real_kitti, out) == 0
    ds = Dataset.open(out)
    assert ds.frame_ids == ["kitti-000000", "kitti-000001", "kitti-000002"]
    sizes = {r.frame_id: (r.width, r.height) for r in ds}
    assert sizes == {"kitti-000000": (1224, 370), "kitti-000001": (1242, 375), "kitti-000002": (1242, 375)}
    cars = 0
    for r in ds:
        calib = kitti.parse_calib((real_kitti / "training/calib" / f"{r.frame_id[-6:]}.txt").read_text(), "calib")
        P2 = calib.projection("P2")
        np.testing.assert_array_equal(r.K, P2[:, :3])
        labels = [lab for lab in kitti.parse_labels(
            (real_kitti / "training/label_2" / f"{r.frame_id[-6:]}.txt").read_text(), "label") if not lab.is_ignore]
        assert len(r.objects) == len(labels)
        t = camera_offset_from_projection(P2)
        assert abs(t[0] - 0.06) < 0.002  # camera 2 sits 6 cm from camera 0: P2's last column is used
        for o, lab in zip(r.objects, labels):
            h = lab.hwl[0]
            np.testing.assert_allclose(o.box.center, np.add(lab.location, [0, -h / 2, 0]) + t, atol=1e-9)
            np.testing.assert_array_equal(o.occluded, self_occluded_corners(o.box))
            assert o.source_attributes == {"class": lab.type, "truncated": lab.truncated,
                                           "occluded": lab.occluded, "alpha": lab.alpha}
            assert o.occlusion_level == lab.occluded
            np.testing.assert_array_equal(o.bbox_source, lab.bbox)
            if o.category == "car":
                cars += 1
                kp = o.keypoints[~o.behind_camera]
                extent = [kp[:, 0].min(), kp[:, 1].min(), kp[:, 0].max(), kp[:, 1].max()]
                np.testing.assert_allclose(extent, lab.bbox, atol=2.0)
    assert cars == 2
    # difficulty: KITTI's easiest level met (2D-box height, occluded, truncated)
    difficulty = {(r.frame_id, o.source_attributes["class"]): o.difficulty for r in ds for o in r.objects}
    assert difficulty == {
        ("kitti-000000", "Pedestrian"): "easy",  # 165 px, visible
        ("kitti-000001", "Truck"): "moderate",  # 33 px
        ("kitti-000001", "Car"): None,  # 22 px: below every level
        ("kitti-000001", "Cyclist"): None,  # occluded 3 (unknown)
        ("kitti-000002", "Misc"): "easy",
        ("kitti-000002", "Car"): "moderate",  # 33 px
    }
    f1 = ds.frame("kitti-000001")
    assert [g.label for g in f1.ignore_regions] == ["DontCare"] * 4
    np.testing.assert_allclose(f1.ignore_regions[0].bbox, [503.89, 169.71, 590.61, 190.13])
    # three objects on the road: a fitted plane near the 1.65 m prior; fewer: the prior itself
    assert 1.5 < f1.camera_height < 1.8 and abs(f1.camera_pitch) < math.radians(3)
    assert not np.allclose(f1.ground_plane.normal, [0, -1, 0])
    for fid in ("kitti-000000", "kitti-000002"):
        r = ds.frame(fid)
        assert r.camera_height == 1.65 and r.camera_pitch == 0.0
        np.testing.assert_array_equal(r.ground_plane.normal, [0, -1, 0])
    assert ds.manifest["conversion_stats"] == {"ground_plane_fitted": 1, "ground_plane_prior": 2,
                                               "objects_outside_image": 0}
    assert main(["validate", str(out)]) == 0


def test_real_frames_from_zips_and_round_trip(real_kitti, tmp_path):
    zips = tmp_path / "zips"
    write_kitti_zips(real_kitti, zips)
    assert convert(real_kitti, tmp_path / "tree") == 0
    assert convert(zips, tmp_path / "zip") == 0
    assert record_texts(tmp_path / "tree") == record_texts(tmp_path / "zip")
    for name in ("kitti-000001.png",):
        assert (tmp_path / "tree/images" / name).read_bytes() == (tmp_path / "zip/images" / name).read_bytes()
    assert main(["export", "kitti", str(tmp_path / "tree"), "--out", str(tmp_path / "exp")]) == 0
    assert convert(tmp_path / "exp", tmp_path / "again") == 0
    assert_same_datasets(tmp_path / "tree", tmp_path / "again")


# ---------------------------------------------------------------------------------------------
# Round trips and equivalences on generated trees
# ---------------------------------------------------------------------------------------------


def test_fixture_frames_convert_and_validate(converted, tree):
    ds = Dataset.open(converted)
    assert len(ds) == 12 and len(ds.objects) > 30
    assert main(["validate", str(converted)]) == 0
    for r in ds:
        with Image.open(tree / "training/image_2" / f"{r.frame_id[-6:]}.png") as im:
            assert (r.width, r.height) == im.size  # read per image: sizes vary
        assert os.path.samefile(converted / r.image, tree / "training/image_2" / f"{r.frame_id[-6:]}.png")
    assert len({(r.width, r.height) for r in ds}) > 1
    stats = ds.manifest["conversion_stats"]
    assert stats["ground_plane_fitted"] + stats["ground_plane_prior"] == 12 and stats["ground_plane_fitted"] > 0


def test_export_then_convert_gives_the_same_records(converted, tree_copy, tmp_path):
    src = tree_copy
    label = next(p for p in sorted((src / "training/label_2").iterdir()) if "Pedestrian " in p.read_text())
    label.write_text(label.read_text().replace("Pedestrian ", "Person_sitting ", 1))  # must survive the trip
    assert convert(src, tmp_path / "a") == 0
    assert main(["export", "kitti", str(tmp_path / "a"), "--out", str(tmp_path / "exp")]) == 0
    exp = tmp_path / "exp"
    assert sorted(p.name for p in exp.iterdir()) == [".omnigen-job", "calib", "image_2", "label_2", "mapping.txt"]
    assert (exp / "mapping.txt").read_text().splitlines()[1] == "000001 kitti-000001"
    calib = kitti.parse_calib((exp / "calib/000001.txt").read_text(), "calib")
    assert set(calib.values) == {"P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo"}
    K = Dataset.open(tmp_path / "a").frame("kitti-000001").K
    np.testing.assert_array_equal(calib.projection("P2"), np.hstack([K, np.zeros((3, 1))]))
    assert os.path.samefile(exp / "image_2/000001.png", tmp_path / "a/images/kitti-000001.png")
    assert convert(exp, tmp_path / "b") == 0
    assert_same_datasets(tmp_path / "a", tmp_path / "b")
    assert "Person_sitting" in (tmp_path / f"b/records/kitti-{label.stem}.json").read_text()


def test_export_derived_values(converted, tmp_path):
    assert main(["export", "kitti", str(converted), "--out", str(tmp_path / "exp"), "--derived"]) == 0
    ds = Dataset.open(converted)
    r = next(r for r in ds if r.objects)
    labels = kitti.parse_labels((tmp_path / "exp/label_2" / f"{r.frame_id[-6:]}.txt").read_text(), "label")
    objects = [lab for lab in labels if not lab.is_ignore]
    assert len(objects) == len(r.objects) and len(labels) - len(objects) == len(r.ignore_regions)
    for o, lab in zip(r.objects, objects):
        assert lab.truncated == o.truncation and lab.occluded == o.occlusion_level
        np.testing.assert_array_equal(lab.bbox, o.bbox)
        x, _, z = lab.location
        assert abs(lab.alpha - kitti_alpha(lab.rotation_y, x, z)) < 1e-12


def test_zip_input_equals_tree_input(tree, converted, tmp_path):
    write_kitti_zips(tree, tmp_path / "zips")
    assert convert(tmp_path / "zips", tmp_path / "ds") == 0
    assert record_texts(tmp_path / "ds") == record_texts(converted)
    assert (tmp_path / "ds/manifest.json").read_bytes() == (converted / "manifest.json").read_bytes()
    for p in (converted / "images").iterdir():
        assert (tmp_path / "ds/images" / p.name).read_bytes() == p.read_bytes()
    # re-zipped under a top folder, and named by one of the archives: the same dataset
    for name in kitti.ARCHIVES.values():
        with zipfile.ZipFile(tmp_path / "zips" / name) as src, zipfile.ZipFile(tmp_path / name, "w") as dst:
            for member in src.namelist():
                dst.writestr(f"KITTI/object/{member}", src.read(member))
    assert convert(tmp_path / kitti.ARCHIVES["calib"], tmp_path / "ds2") == 0
    assert record_texts(tmp_path / "ds2") == record_texts(converted)


def test_rerun_is_byte_identical(tree, converted, tmp_path):
    before = record_texts(converted), (converted / "manifest.json").read_bytes()
    assert convert(tree, converted) == 0
    assert (record_texts(converted), (converted / "manifest.json").read_bytes()) == before
    assert convert(tree, tmp_path / "elsewhere") == 0  # nothing depends on where the output lives
    assert record_texts(tmp_path / "elsewhere") == before[0]


def test_interrupted_run_then_rerun_gives_the_same_dataset(tree, converted, tmp_path, monkeypatch, capsys):
    out = tmp_path / "ds"
    real = kitti.KittiConverter.convert_one
    calls = []

    def interrupted(self, kid):
        calls.append(kid)
        if len(calls) == 6:
            raise KeyboardInterrupt
        return real(self, kid)

    monkeypatch.setattr(kitti.KittiConverter, "convert_one", interrupted)
    assert convert(tree, out, "--workers", "1") == 130
    assert "rerun resumes" in capsys.readouterr().err
    finished = record_texts(out)
    assert len(finished) == 5 and not (out / "manifest.json").exists()
    assert not any(p.name.startswith(".tmp-") for p in (out / "records").iterdir())
    for name, text in finished.items():  # what is there is finished, and final
        assert text == record_texts(converted)[name]
    monkeypatch.setattr(kitti.KittiConverter, "convert_one", real)
    assert convert(tree, out) == 0
    assert record_texts(out) == record_texts(converted)
    assert (out / "manifest.json").read_bytes() == (converted / "manifest.json").read_bytes()


def test_a_rerun_keeps_no_frame_an_earlier_run_left(tree, tree_copy, converted, tmp_path, capsys):
    # a smaller --limit, then a frame whose label turned bad: the dataset holds this run's frames only
    out = tmp_path / "ds"
    shutil.copytree(converted, out)
    assert convert(tree, out, "--limit", "3") == 0
    assert "removed 9 frames an earlier run left" in capsys.readouterr().out
    ds = Dataset.open(out)
    assert len(ds) == 3 and ds.manifest["counts"]["frames"] == 3
    assert sorted(p.name for p in (out / "images").iterdir()) == sorted(Path(r.image).name for r in ds)
    src = tree_copy
    (src / "training" / "label_2" / "000002.txt").write_text("Car 0.0 0 not-a-number\n")
    assert convert(src, out, "--limit", "3") == 1  # the bad frame is skipped ...
    assert sorted(Dataset.open(out).frame_ids) == ["kitti-000000", "kitti-000001"]  # ... and its old record gone
    assert not (out / "images" / "kitti-000002.png").exists()


def test_convert_refuses_an_output_folder_it_did_not_make(tree, tmp_path, capsys):
    from omnigen.fakes import write_fake_dataset

    unfinished = write_fake_dataset(tmp_path / "render", n_frames=3, seed=1).root  # say, a render's output
    (unfinished / "manifest.json").unlink()
    before = record_texts(unfinished)
    assert convert(tree, unfinished) == 1
    assert "did not make; refusing to overwrite" in capsys.readouterr().err
    assert record_texts(unfinished) == before and not (unfinished / ".omnigen-job").exists()


def test_interruption_inside_run_conversion_propagates(tree, tmp_path):
    converter = kitti.KittiConverter(kitti.open_input(tree, "training"), "training")
    keys = converter.keys()

    def convert_one(kid):
        if kid == keys[3]:
            raise KeyboardInterrupt
        return converter.convert_one(kid)

    with pytest.raises(KeyboardInterrupt):
        run_conversion(keys, convert_one, tmp_path / "ds")
    assert sorted(record_texts(tmp_path / "ds")) == [f"kitti-{k}.json" for k in keys[:3]]


@pytest.fixture(scope="module")
def big_tree(tmp_path_factory) -> Path:
    """Enough frames for the worker processes to start, one of them bad; and its serial conversion."""
    root = tmp_path_factory.mktemp("kitti-big")
    write_kitti_tree(root / "src", PARALLEL_MIN_FRAMES + 6, seed=9)
    (root / "src/training/label_2/000007.txt").write_text("Car 0 0 0 1 2 3\n")  # one bad frame
    assert convert(root / "src", root / "serial", "--workers", "1") == 1
    return root


def test_workers_give_the_same_dataset_as_one_process(big_tree, tmp_path, capsys, monkeypatch):
    from omnigen.record import FrameRecord
    write_kitti_zips(big_tree / "src", tmp_path / "zips")
    capsys.readouterr()
    parsed = []
    real_from_dict = FrameRecord.from_dict.__func__
    monkeypatch.setattr(FrameRecord, "from_dict", classmethod(lambda cls, *a, **k: parsed.append(1) or real_from_dict(cls, *a, **k)))
    assert convert(big_tree / "src", tmp_path / "parallel", "--workers", "2") == 1
    assert not parsed  # workers validated; this process indexes their records without parsing any again
    monkeypatch.undo()
    assert convert(tmp_path / "zips", tmp_path / "zip-parallel", "--workers", "3") == 1  # each worker reopens the zips
    skipped = [line for line in capsys.readouterr().out.splitlines() if "skipped:" in line]
    assert len(skipped) == 2 and all("000007.txt: line 1: expected 15 fields" in line for line in skipped)
    expected = record_texts(big_tree / "serial")
    assert len(expected) == PARALLEL_MIN_FRAMES + 5
    for other in ("parallel", "zip-parallel"):
        assert record_texts(tmp_path / other) == expected
        assert (tmp_path / other / "manifest.json").read_bytes() == (big_tree / "serial/manifest.json").read_bytes()


def test_workers_strict_and_interrupted(big_tree, tmp_path, monkeypatch, capsys):
    assert convert(big_tree / "src", tmp_path / "strict", "--workers", "2", "--strict") == 1
    assert "000007.txt: line 1: expected 15 fields" in capsys.readouterr().err
    assert not (tmp_path / "strict/manifest.json").exists()
    real = kitti.KittiConverter.convert_one

    def interrupted(self, kid):  # runs in the workers: they carry the interruption back
        if kid == "000040":
            raise KeyboardInterrupt
        return real(self, kid)

    monkeypatch.setattr(kitti.KittiConverter, "convert_one", interrupted)
    out = tmp_path / "ds"
    assert convert(big_tree / "src", out, "--workers", "2") == 130
    assert not (out / "manifest.json").exists() and "kitti-000040.json" not in record_texts(out)
    monkeypatch.setattr(kitti.KittiConverter, "convert_one", real)
    assert convert(big_tree / "src", out, "--workers", "2") == 1  # the bad frame is still bad
    assert record_texts(out) == record_texts(big_tree / "serial")
    assert (out / "manifest.json").read_bytes() == (big_tree / "serial/manifest.json").read_bytes()


def test_testing_split(tmp_path):
    write_kitti_tree(tmp_path / "src", 3, split="testing")
    assert not (tmp_path / "src/testing/label_2").exists()
    assert convert(tmp_path / "src", tmp_path / "ds", "--split", "testing") == 0
    ds = Dataset.open(tmp_path / "ds")
    assert ds.frame_ids == ["kitti-testing-000000", "kitti-testing-000001", "kitti-testing-000002"]
    assert all(not r.objects and r.camera_height == 1.65 for r in ds)
    write_kitti_zips(tmp_path / "src", tmp_path / "zips")  # no label archive needed for testing
    (tmp_path / "zips" / kitti.ARCHIVES["label_2"]).unlink()
    assert convert(tmp_path / "zips", tmp_path / "zds", "--split", "testing") == 0
    assert record_texts(tmp_path / "zds") == record_texts(tmp_path / "ds")


def test_objects_with_no_part_in_the_image_are_left_out_and_counted(tree_copy, tmp_path):
    src = tree_copy
    label = src / "training/label_2/000002.txt"
    lines = label.read_text().splitlines()
    behind = "Car 0.00 0 0.00 0.00 0.00 1.00 1.00 1.50 1.60 3.90 0.00 1.65 -10.00 0.00"
    label.write_text("\n".join([behind, *lines]) + "\n")
    assert convert(src, tmp_path / "ds") == 0
    ds = Dataset.open(tmp_path / "ds")
    assert ds.manifest["conversion_stats"]["objects_outside_image"] == 1
    kept = ds.frame("kitti-000002").objects
    assert len(kept) == sum(1 for line in lines if not line.startswith("DontCare"))
    assert [o.instance_id for o in kept] == list(range(1, len(kept) + 1))


# ---------------------------------------------------------------------------------------------
# Bad input: every error names the file (and the line where there is one)
# ---------------------------------------------------------------------------------------------


def _append_line(path: Path, line: str) -> int:
    lines = path.read_text().splitlines()
    path.write_text("\n".join([*lines, line]) + "\n")
    return len(lines) + 1


def break_field_count(src: Path) -> tuple[str, str]:
    n = _append_line(src / "training/label_2/000004.txt", "Car 0.00 0 1.0 10 10 20 20 1.5 1.6 3.9 1.0 1.6")
    return "training/label_2/000004.txt", f"line {n}: expected 15 fields"


def break_number(src: Path) -> tuple[str, str]:
    n = _append_line(src / "training/label_2/000004.txt", "Car 0.00 0 1.0 10 10 20 20 1.5 1.6 3.9 1.0 abc 20 0.1")
    return "training/label_2/000004.txt", f"line {n}: y: 'abc' is not a number"


def break_calib(src: Path) -> tuple[str, str]:
    path = src / "training/calib/000004.txt"
    path.write_text("".join(line + "\n" for line in path.read_text().splitlines() if not line.startswith("P2")))
    return "training/calib/000004.txt", "P2: no P2 line"


def break_calib_number(src: Path) -> tuple[str, str]:
    path = src / "training/calib/000004.txt"
    path.write_text(path.read_text().replace("P2: ", "P2: x", 1))
    return "training/calib/000004.txt", "line 3: P2 value 1: 'x"


def remove_image(src: Path) -> tuple[str, str]:
    (src / "training/image_2/000004.png").unlink()
    return "training/image_2/000004.png", "image missing"


def corrupt_image(src: Path) -> tuple[str, str]:
    (src / "training/image_2/000004.png").write_bytes(b"this is not a png")
    return "training/image_2/000004.png", "unreadable image"


@pytest.mark.parametrize("breaker", [break_field_count, break_number, break_calib, break_calib_number,
                                     remove_image, corrupt_image])
def test_bad_frame_is_skipped_listed_and_fails_the_run(breaker, tree_copy, tmp_path, capsys):
    src = tree_copy
    file, message = breaker(src)
    assert convert(src, tmp_path / "ds") == 1
    out = capsys.readouterr().out
    assert f"skipped: {src / file}: {message}" in out, out
    ds = Dataset.open(tmp_path / "ds")
    assert len(ds) == 11 and "kitti-000004" not in ds.frame_ids
    assert not (tmp_path / "ds/images/kitti-000004.png").exists()


@pytest.mark.parametrize("breaker", [break_field_count, break_calib, corrupt_image])
def test_strict_stops_at_the_first_bad_frame(breaker, tree_copy, tmp_path, capsys):
    src = tree_copy
    file, message = breaker(src)
    assert convert(src, tmp_path / "ds", "--strict") == 1
    err = capsys.readouterr().err
    assert f"{src / file}: {message}" in err and "Traceback" not in err
    assert not (tmp_path / "ds/manifest.json").exists()  # never finalized
    assert len(record_texts(tmp_path / "ds")) == 4  # frames 0-3, then the stop


def test_bad_frames_in_archives_name_archive_and_member(tree_copy, tmp_path, capsys):
    src = tree_copy
    _, message = break_number(src)
    write_kitti_zips(src, tmp_path / "zips")
    assert convert(tmp_path / "zips", tmp_path / "ds") == 1
    archive = tmp_path / "zips" / kitti.ARCHIVES["label_2"]
    assert f"skipped: {archive}:training/label_2/000004.txt: {message}" in capsys.readouterr().out


def test_wrong_archives_stop_the_run(tree, tmp_path, capsys):
    zips = tmp_path / "zips"
    write_kitti_zips(tree, zips)
    images = zips / kitti.ARCHIVES["image_2"]
    labels = zips / kitti.ARCHIVES["label_2"]
    shutil.copy(images, labels)  # the image archive under the label archive's name
    assert convert(zips, tmp_path / "ds") == 1
    err = capsys.readouterr().err
    assert f"{labels}: not the KITTI archive data_object_label_2.zip" in err and "training/image_2/" in err
    labels.write_bytes(b"not a zip at all")
    assert convert(zips, tmp_path / "ds") == 1
    assert f"{labels}: not a zip archive" in capsys.readouterr().err
    labels.unlink()
    assert convert(zips, tmp_path / "ds") == 1
    assert "archive(s) missing: data_object_label_2.zip" in capsys.readouterr().err
    assert not (tmp_path / "ds/manifest.json").exists()


def test_nothing_to_convert_is_an_error(tmp_path, capsys):
    assert convert(tmp_path / "nowhere", tmp_path / "ds") == 1
    assert "does not exist" in capsys.readouterr().err
    (tmp_path / "src/training/image_2").mkdir(parents=True)
    (tmp_path / "src/training/calib").mkdir(parents=True)
    assert convert(tmp_path / "src", tmp_path / "ds") == 1
    assert "training/label_2: folder missing (the testing split has no labels" in capsys.readouterr().err
    (tmp_path / "src/training/label_2").mkdir(parents=True)
    assert convert(tmp_path / "src", tmp_path / "ds") == 1
    assert "no training frames found" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------------
# The pieces
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("height, occluded, truncated, expected", [
    (40.0, 0, 0.15, "easy"),
    (39.9, 0, 0.0, "moderate"),
    (60.0, 1, 0.0, "moderate"),
    (60.0, 0, 0.16, "moderate"),
    (25.0, 1, 0.30, "moderate"),
    (25.0, 2, 0.30, "hard"),
    (60.0, 0, 0.5, "hard"),
    (24.9, 0, 0.0, None),
    (60.0, 3, 0.0, None),
    (60.0, 0, 0.51, None),
])
def test_difficulty(height, occluded, truncated, expected):
    assert kitti.kitti_difficulty(height, occluded, truncated) == expected


def test_ground_plane_fit_and_fallbacks():
    from omnigen.formats.kitti import box_from_kitti, kitti_rotation
    from omnigen.geometry import Box3D, plane_from_height_pitch, rot_x
    truth = plane_from_height_pitch(1.7, math.radians(2.0))

    def standing(x, z, plane):
        # bottom centre on the plane, box upright along the plane's normal
        y = -(plane.normal[0] * x + plane.normal[2] * z + plane.offset) / plane.normal[1]
        r = rot_x(math.radians(2.0)) @ kitti_rotation(0.3)
        up = r[:, 2]
        return Box3D(np.array([x, y, z]) + up * 0.75, [4.0, 1.7, 1.5], r)

    boxes = [standing(x, z, truth) for x, z in [(-4, 12), (3, 20), (0, 35), (6, 9)]]
    plane, fitted = kitti.ground_plane(boxes)
    assert fitted
    np.testing.assert_allclose(plane.normal, truth.normal, atol=1e-9)
    assert abs(plane.camera_height - 1.7) < 1e-9
    prior = (np.array([0.0, -1.0, 0.0]), 1.65)
    upright = lambda x, y, z: box_from_kitti(1.7, 0.5, 0.5, x, y, z, 0.3)  # noqa: E731 (pedestrians; y: the bottom)
    for few_or_odd in (boxes[:2],  # fewer than three objects
                       [upright(-2, 0.8, 10), upright(2, 2.8, 10), upright(0, 1.8, 20)],  # road rolled 27 deg
                       [upright(-3, 3.0, 10), upright(3, 3.0, 10), upright(0, 3.0, 20)],  # camera 3 m up
                       [upright(-3, 1.6, 10), upright(3, 1.6, 10), upright(0, 4.0, 20)],  # one bottom implausible
                       [upright(-3, 1.6, 10), upright(3, 1.6, 10), upright(0, 1.6, 90)]):  # one too far
        plane, fitted = kitti.ground_plane(few_or_odd)
        assert not fitted
        np.testing.assert_array_equal(plane.normal, prior[0])
        assert plane.offset == prior[1]


def test_parse_errors_name_file_and_line():
    with pytest.raises(kitti.SourceError, match=r"^lab: line 2: unknown class 'Bus'"):
        kitti.parse_labels("\nBus 0 0 0 1 1 2 2 1 1 1 0 1 10 0\n", "lab")
    with pytest.raises(kitti.SourceError, match=r"^lab: line 1: occluded must be 0, 1, 2 or 3, got 1.5"):
        kitti.parse_labels("Car 0 1.5 0 1 1 2 2 1 1 1 0 1 10 0\n", "lab")
    with pytest.raises(kitti.SourceError, match=r"^lab: line 1: x: 'nan' is not finite"):
        kitti.parse_labels("Car 0 0 0 1 1 2 2 1 1 1 nan 1 10 0\n", "lab")
    with pytest.raises(kitti.SourceError, match=r"^lab: line 1: dimensions"):
        kitti.parse_labels("Car 0 0 0 1 1 2 2 0 1 1 0 1 10 0\n", "lab")
    with pytest.raises(kitti.SourceError, match=r"^cal: line 1: expected 'NAME: numbers'"):
        kitti.parse_calib("P2 1 2 3\n", "cal")
    with pytest.raises(kitti.SourceError, match=r"^cal: line 1: P2 needs 12 numbers, got 3"):
        kitti.parse_calib("P2: 1 2 3\n", "cal").projection("P2")
    dont_care = kitti.parse_labels("DontCare -1 -1 -10 5 6 7 8 -1 -1 -1 -1000 -1000 -1000 -10\n", "lab")
    assert dont_care[0].is_ignore and dont_care[0].bbox == (5, 6, 7, 8)


def test_export_of_other_sources_pitched_camera_and_classes(tmp_path):
    """Non-KITTI records: derived values, sequential numbers, Misc for classes KITTI lacks, and
    rotation_y / location for a pitched camera (the centre comes back exactly, the tilt is lost)."""
    from omnigen.formats.kitti import kitti_alpha, kitti_rotation, label_line
    from omnigen.writer import DatasetWriter
    from omnigen.camera import intrinsics_from_fov
    from omnigen.geometry import Box3D, rot_x
    from omnigen.record import FrameRecord, ObjectRecord

    K = intrinsics_from_fov(math.radians(60), 320, 240)
    pitch = math.radians(20)
    ry = 0.7
    box = Box3D([1.0, 2.0, 15.0], [11.0, 2.6, 3.2], rot_x(-pitch) @ kitti_rotation(ry))
    bus = ObjectRecord.from_box("bus", 7, box, K, 320, 240, occlusion_level=1)
    writer = DatasetWriter(tmp_path / "ds")
    (tmp_path / "ds/images").mkdir()
    for i in (5, 9):
        fid = f"dair-v2x-i-00000{i}"
        (tmp_path / f"ds/images/{fid}.jpg").write_bytes(b"jpeg")
        writer.write(FrameRecord(fid, "dair-v2x-i", "infrastructure", f"images/{fid}.jpg", 320, 240, K, [bus]))
    writer.finalize()
    assert main(["export", "kitti", str(tmp_path / "ds"), "--out", str(tmp_path / "exp")]) == 0
    assert (tmp_path / "exp/mapping.txt").read_text() == "000000 dair-v2x-i-000005\n000001 dair-v2x-i-000009\n"
    assert (tmp_path / "exp/image_2/000001.jpg").read_bytes() == b"jpeg"
    (lab,) = kitti.parse_labels((tmp_path / "exp/label_2/000000.txt").read_text(), "label")
    assert lab.type == "Misc" and lab.occluded == 1 and lab.truncated == bus.truncation
    h = lab.hwl[0]
    np.testing.assert_allclose(np.add(lab.location, [0, -h / 2, 0]), box.center, atol=1e-12)
    forward = box.forward
    assert abs(lab.rotation_y - math.atan2(-forward[2], forward[0])) < 1e-12
    assert abs(lab.alpha - kitti_alpha(lab.rotation_y, lab.location[0], lab.location[2])) < 1e-12
    assert label_line(FrameRecord("x", "kitti", "ego", "i", 1, 1, K), bus).startswith("Misc ")


def test_kitti_file_names():
    assert kitti_file_names(["kitti-000007", "kitti-000003"]) == {"kitti-000007": "000007", "kitti-000003": "000003"}
    assert kitti_file_names(["kitti-000007", "kitti-testing-000007"]) == {
        "kitti-000007": "000000", "kitti-testing-000007": "000001"}
    assert kitti_file_names(["synthetic-b", "synthetic-a"]) == {"synthetic-a": "000000", "synthetic-b": "000001"}


def test_fixture_is_deterministic_per_frame(tmp_path):
    write_kitti_tree(tmp_path / "a", 3, seed=1)
    write_kitti_tree(tmp_path / "b", 5, seed=1)
    write_kitti_tree(tmp_path / "c", 3, seed=2)
    for folder, name in [("label_2", "000002.txt"), ("calib", "000002.txt"), ("image_2", "000002.png")]:
        a = (tmp_path / "a/training" / folder / name).read_bytes()
        assert a == (tmp_path / "b/training" / folder / name).read_bytes()
    assert (tmp_path / "a/training/calib/000002.txt").read_bytes() != (tmp_path / "c/training/calib/000002.txt").read_bytes()
    write_kitti_zips(tmp_path / "a", tmp_path / "z")
    with zipfile.ZipFile(tmp_path / "z" / kitti.ARCHIVES["image_2"]) as zf:
        assert zf.namelist() == [f"training/image_2/00000{i}.png" for i in range(3)]
