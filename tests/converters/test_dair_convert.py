"""`omnigen convert dair`: DAIR-V2X-I and DAIR-V2X-C (infrastructure side) into UrbanOmniView.

Geometry is checked against projections computed here, independently of omnigen.geometry: the
eight corners are built by hand in the virtual-LiDAR frame and projected with cv2.projectPoints
using the extrinsics read straight from the calibration files.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

from omnigen.converters import dair
from omnigen.converters.dair_fixture import I_RUN, C_BATCH, tiny_jpeg, write_dair_tree
from omnigen.cli import main
from omnigen.dataset import Dataset
from omnigen.geometry import is_rotation

REALDATA = Path(__file__).resolve().parents[2].parent / "shared" / "realdata"
REAL_LABEL = REALDATA / "dair-v2x-c" / "infrastructure-side" / "label" / "virtuallidar" / "001366.json"

CORNER_SIGNS = [(1, 1, 1), (1, -1, 1), (-1, -1, 1), (-1, 1, 1), (1, 1, -1), (1, -1, -1), (-1, -1, -1), (-1, 1, -1)]


# ---------------------------------------------------------------------------------------------
# Helpers (independent of the converter)
# ---------------------------------------------------------------------------------------------


def convert(src: Path, out: Path, capsys, *extra: str) -> tuple[int, str, str]:
    code = main(["convert", "dair", str(src), "--out", str(out), "--workers", "1", *extra])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def read(path: Path):
    return json.loads(path.read_text())


def extrinsics_from_file(path: Path) -> tuple[np.ndarray, np.ndarray]:
    calib = read(path)
    if "Tr_velo_to_cam" in calib:
        m = np.array(calib["Tr_velo_to_cam"], dtype=np.float64).reshape(3, 4)
        return m[:, :3], m[:, 3]
    return np.array(calib["rotation"], dtype=np.float64), np.array(calib["translation"], dtype=np.float64).reshape(3)


def label_corners_lidar(obj: dict) -> np.ndarray:
    """The contract's eight corners, by hand: forward = (cos, sin, 0), left = (-sin, cos, 0), up = z."""
    d, loc, yaw = obj["3d_dimensions"], obj["3d_location"], float(obj["rotation"])
    l, w, h = float(d["l"]), float(d["w"]), float(d["h"])
    centre = np.array([float(loc["x"]), float(loc["y"]), float(loc["z"])])
    forward, left, up = np.array([math.cos(yaw), math.sin(yaw), 0.0]), np.array([-math.sin(yaw), math.cos(yaw), 0.0]), np.array([0.0, 0.0, 1.0])
    return np.array([centre + sx * l / 2 * forward + sy * w / 2 * left + sz * h / 2 * up for sx, sy, sz in CORNER_SIGNS])


def project_cv2(corners: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray) -> np.ndarray:
    rvec, _ = cv2.Rodrigues(R)
    uv, _ = cv2.projectPoints(corners.reshape(-1, 1, 3), rvec, t.reshape(3, 1), K, None)
    return uv.reshape(-1, 2)


def records(out: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted((out / "records").glob("*.json"))}


@pytest.fixture(scope="module")
def tree_i(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("dair-i") / "single-infrastructure-side"
    write_dair_tree(root, 2 * I_RUN, seed=3, variant="i")
    return root


@pytest.fixture(scope="module")
def converted_i(tree_i, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("out-i")
    assert main(["convert", "dair", str(tree_i), "--out", str(out), "--workers", "1"]) == 0
    return out


# ---------------------------------------------------------------------------------------------
# The real label file
# ---------------------------------------------------------------------------------------------


def real_label() -> Path:
    if not REAL_LABEL.is_file():
        pytest.skip(f"real DAIR-V2X-C label not found at {REAL_LABEL} (../shared/realdata is absent)")
    return REAL_LABEL


def test_real_label_parses_with_its_quirks():
    path = real_label()
    parsed = dair.parse_label(dair.read_json(path), path)
    assert [o.category for o in parsed.objects] == ["motorcyclist"] * 3 + ["car"] * 3 + ["traffic_cone", "car"]
    assert parsed.ignore_regions == []
    raw = read(path)
    for o in parsed.objects:
        given = raw[o.index]
        # the source's own fields stay exactly as given (strings stay strings)
        assert {k: o.attributes[k] for k in ("type", "truncated_state", "occluded_state", "alpha")} == \
            {k: given[k] for k in ("type", "truncated_state", "occluded_state", "alpha")}
        assert o.occlusion_level == int(given["occluded_state"])
    assert parsed.objects[6].attributes["type"] == "Trafficcone"
    assert parsed.objects[4].occlusion_level == 1
    # the ground under these boxes: nearly level in the virtual-LiDAR frame, about 1.7 m below its origin
    ground = dair.estimate_ground(parsed.objects)
    assert ground.method == "fit"
    assert math.degrees(math.acos(ground.plane.normal[2])) < 1.0
    assert -2.0 < -ground.plane.offset < -1.5


def _lidar_object(i: int, center, lwh, yaw: float) -> dair.LabelObject:
    return dair.LabelObject(i, "car", np.asarray(center, dtype=np.float64), np.asarray(lwh, dtype=np.float64), yaw,
                            np.zeros(4), 0, {})


def test_bottom_corners_and_ground_estimate_policy():
    """bottom_corners (geometry.cuboid_corners in the LiDAR frame) against the hand-built corners 4-7,
    then the converter's own policy around the shared fit: a fit from five objects, none tilted
    beyond PLANE_MAX_TILT_DEG, else the level plane at the median bottom."""
    rng = np.random.default_rng(3)
    objects = [_lidar_object(i, rng.uniform([-20, -20, -6], [40, 20, -4]), rng.uniform(0.5, 10, 3), rng.uniform(-7, 7))
               for i in range(12)]
    for o, bottoms in zip(objects, dair.bottom_corners(objects)):
        d = {"3d_dimensions": dict(zip("lwh", o.lwh)), "3d_location": dict(zip("xyz", o.center)), "rotation": o.yaw}
        np.testing.assert_allclose(bottoms, label_corners_lidar(d)[4:], atol=1e-12)

    def on_slope(n: int, tilt_deg: float) -> list:
        # boxes standing on the plane z = -5 + tan(tilt) x (a slope rising along the LiDAR's x)
        grade = math.tan(math.radians(tilt_deg))
        xs = np.linspace(5.0, 45.0, n)
        ys = np.resize([-6.0, 3.0, 8.0], n)
        return [_lidar_object(i, [x, y, -5.0 + grade * x + 0.8], [4.0, 1.8, 1.6], 0.3 * i) for i, (x, y) in enumerate(zip(xs, ys))]

    fit = dair.estimate_ground(on_slope(5, 3.0))
    assert fit.method == "fit"
    # upright boxes: each flat bottom touches the slope at its centre only, so the fit is near 3 degrees
    assert math.degrees(math.acos(fit.plane.normal[2])) == pytest.approx(3.0, abs=0.1)
    steep = on_slope(6, 8.0)  # beyond the 6 degree limit: level at the median bottom
    level = dair.estimate_ground(steep)
    assert level.method == "level"
    np.testing.assert_array_equal(level.plane.normal, [0.0, 0.0, 1.0])
    assert -level.plane.offset == pytest.approx(float(np.median([o.center[2] - 0.8 for o in steep])))
    assert dair.estimate_ground(on_slope(4, 3.0)).method == "level"  # fewer than PLANE_MIN_OBJECTS
    assert dair.estimate_ground([]) is None


def test_real_label_converts_under_a_pole_camera(tmp_path, capsys):
    """The real file, as label/virtuallidar of a frame with a 7 m pole camera pitched 15 degrees."""
    path = real_label()
    root = tmp_path / "infrastructure-side"
    write_dair_tree(root, 1, variant="c", image_size=(1920, 1080))
    shutil.copyfile(path, root / "label/virtuallidar/000000.json")
    pitch, ground_z, height = math.radians(15.0), -1.73, 7.0
    level = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    c, s = math.cos(-pitch), math.sin(-pitch)
    R = (level @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]])).T
    t = -R @ np.array([0.0, 0.0, ground_z + height])
    (root / "calib/virtuallidar_to_camera/000000.json").write_text(
        json.dumps({"rotation": R.tolist(), "translation": t.reshape(3, 1).tolist()}))
    (root / "calib/camera_intrinsic/000000.json").write_text(
        json.dumps({"cam_D": [0] * 5, "cam_K": [2100.0, 0, 959.5, 0, 2100.0, 539.5, 0, 0, 1]}))
    code, out, _ = convert(root, tmp_path / "out", capsys, "--label", "virtuallidar")
    assert code == 0, out
    rec = Dataset.open(tmp_path / "out")[0]
    assert [o.category for o in rec.objects].count("car") == 4
    assert abs(rec.camera_height - height) < 0.1
    assert abs(math.degrees(rec.camera_pitch) - 15.0) < 0.5
    for o in rec.objects:
        assert o.source_attributes["label_set"] == "virtuallidar"
        assert isinstance(o.source_attributes["alpha"], str)


# ---------------------------------------------------------------------------------------------
# Geometry on fixture frames
# ---------------------------------------------------------------------------------------------


def test_keypoints_match_independent_projection(tree_i, converted_i):
    ds = Dataset.open(converted_i)
    checked = inside = 0
    for rec in ds:
        key = rec.frame_id.removeprefix("dair-v2x-i-")
        R, t = extrinsics_from_file(tree_i / f"calib/virtuallidar_to_camera/{key}.json")
        K = np.array([float(v) for v in read(tree_i / f"calib/camera_intrinsic/{key}.json")["cam_K"]]).reshape(3, 3)
        labels = read(tree_i / f"label/camera/{key}.json")
        for o in rec.objects:
            uv = project_cv2(label_corners_lidar(labels[o.instance_id - 1]), R, t, K)
            assert not o.behind_camera.any()
            np.testing.assert_allclose(o.keypoints, uv, atol=1e-6)
            lo, hi = uv.min(axis=0), uv.max(axis=0)
            clipped = np.array([max(lo[0], -0.5), max(lo[1], -0.5), min(hi[0], rec.width - 0.5), min(hi[1], rec.height - 0.5)])
            # the in-image silhouette lies inside the clipped extent of the corners
            assert (o.bbox[:2] >= clipped[:2] - 1e-6).all() and (o.bbox[2:] <= clipped[2:] + 1e-6).all()
            if o.in_image.all():  # wholly inside: the box is exactly the extent, and so is the label's 2d_box
                np.testing.assert_allclose(o.bbox, [*lo, *hi], atol=1e-6)
                np.testing.assert_allclose(o.bbox_source, o.bbox, atol=1e-6)
                inside += 1
            checked += 1
    assert checked > 50 and inside > 20


def test_heading_is_along_lidar_x_and_top_is_lidar_up(tmp_path, capsys):
    root = tmp_path / "infrastructure-side"
    fx = write_dair_tree(root, 1, seed=5, variant="i")
    cam = fx.cameras[0]
    look = cam.rotation[2, :2] / np.linalg.norm(cam.rotation[2, :2])  # the optical axis over the ground
    side = np.array([-look[1], look[0]])
    objects = []
    for k, yaw in enumerate((0.0, math.pi / 2)):
        at = cam.center[:2] + 25.0 * look + (3.0 * k - 1.5) * side
        objects.append({"type": "Car", "truncated_state": "0", "occluded_state": "0", "alpha": "0",
                        "2d_box": {"xmin": 0, "ymin": 0, "xmax": 10, "ymax": 10},
                        "3d_dimensions": {"h": 1.5, "w": 1.8, "l": 4.5},
                        "3d_location": {"x": at[0], "y": at[1], "z": cam.ground_z + 0.75},
                        "rotation": yaw})
    (root / "label/camera/000000.json").write_text(json.dumps(objects))
    assert convert(root, tmp_path / "out", capsys)[0] == 0
    rec = Dataset.open(tmp_path / "out")[0]
    R, t = extrinsics_from_file(root / "calib/virtuallidar_to_camera/000000.json")
    boxes = {o.instance_id: o.box for o in rec.objects}
    assert set(boxes) == {1, 2}
    for instance, forward_axis, left_axis in ((1, 0, 1), (2, 1, 0)):
        box = boxes[instance]
        lidar = (box.corners() - t) @ R  # X_lidar = R^T (X_cam - t)
        sign = 1 if instance == 1 else -1  # yaw 90 degrees: left is -x
        assert np.allclose(lidar[[0, 1, 4, 5], forward_axis] - lidar[[3, 2, 7, 6], forward_axis], 4.5)
        assert np.allclose(sign * (lidar[[0, 3, 4, 7], left_axis] - lidar[[1, 2, 5, 6], left_axis]), 1.8)
        assert np.allclose(lidar[:4, 2] - lidar[4:, 2], 1.5)  # top above bottom in the LiDAR's z
        assert np.allclose(lidar[4:, 2], cam.ground_z)
        # pitched camera: the box's up is the LiDAR's up seen from the camera, not the camera's -y
        np.testing.assert_allclose(box.up, R[:, 2], atol=1e-12)
        assert abs(box.up @ np.array([0.0, -1.0, 0.0])) < math.cos(math.radians(9.0))


def test_top_corners_are_higher_on_every_object(tree_i, converted_i):
    for rec in Dataset.open(converted_i):
        key = rec.frame_id.removeprefix("dair-v2x-i-")
        R, t = extrinsics_from_file(tree_i / f"calib/virtuallidar_to_camera/{key}.json")
        for o in rec.objects:
            z = ((o.box.corners() - t) @ R)[:, 2]
            assert (z[:4] > z[4:] + 0.1).all()
            assert is_rotation(o.box.rotation, 1e-9)


def test_camera_height_and_pitch_from_the_ground(tmp_path, capsys):
    root = tmp_path / "infrastructure-side"
    fx = write_dair_tree(root, 6, seed=11, variant="c")
    for key in ("000004", "000005"):  # no objects: no ground height, pitch from the extrinsics alone
        (root / f"label/camera/{key}.json").write_text("[]")
    code, out, _ = convert(root, tmp_path / "out", capsys)
    assert code == 0
    assert "none (no objects) in 2" in out
    for rec, cam in zip(Dataset.open(tmp_path / "out"), fx.cameras):
        assert abs(rec.camera_pitch - cam.pitch) < 1e-9
        assert 6.0 <= cam.height <= 10.0 and 10.0 <= math.degrees(cam.pitch) <= 25.0
        if rec.objects:
            assert abs(rec.camera_height - cam.height) < 1e-9
            assert abs(rec.ground_plane.camera_height - cam.height) < 1e-9
        else:
            assert rec.camera_height is None and rec.ground_plane is None


def test_objects_outside_the_image_are_left_out(tmp_path, capsys):
    root = tmp_path / "infrastructure-side"
    fx = write_dair_tree(root, 1, seed=2, variant="i")
    labels = read(root / "label/camera/000000.json")
    behind = dict(labels[0], type="Car")
    behind["3d_location"] = {"x": fx.cameras[0].center[0] - 30.0, "y": 0.0, "z": fx.cameras[0].ground_z + 0.75}
    behind["3d_dimensions"] = {"h": 1.5, "w": 1.8, "l": 4.5}
    (root / "label/camera/000000.json").write_text(json.dumps(labels + [behind]))
    code, out, _ = convert(root, tmp_path / "out", capsys)
    assert code == 0 and "left out): 1" in out
    rec = Dataset.open(tmp_path / "out")[0]
    assert len(labels) + 1 not in [o.instance_id for o in rec.objects]
    assert Dataset.open(tmp_path / "out").manifest["conversion_stats"]["objects_outside_image"] == 1


# ---------------------------------------------------------------------------------------------
# Format variants
# ---------------------------------------------------------------------------------------------


def test_classes_strings_and_ignore_regions(tree_i, converted_i):
    ds = Dataset.open(converted_i)
    types, ignored = set(), []
    for rec in ds:
        labels = read(tree_i / f"label/camera/{rec.frame_id.removeprefix('dair-v2x-i-')}.json")
        ignored += [r.label for r in rec.ignore_regions]
        for o in rec.objects:
            given = labels[o.instance_id - 1]
            types.add(given["type"])
            assert o.category == dair.DAIR_CLASSES[given["type"].lower()]
            assert o.occlusion_level == int(given["occluded_state"])
            assert o.source_attributes["occluded_state"] == given["occluded_state"]  # kept as given: a string
            np.testing.assert_array_equal(o.bbox_source, [given["2d_box"][k] for k in ("xmin", "ymin", "xmax", "ymax")])
    assert any(t.islower() for t in types) and any(t.isupper() for t in types)  # mixed case on purpose
    assert ignored and set(ignored) <= {"Unknown", "ignore"}
    assert any(isinstance(o["3d_location"]["x"], str) for p in (tree_i / "label/camera").glob("*.json") for o in read(p))


@pytest.mark.parametrize("variant", ["i", "c"])
def test_both_data_info_spellings_give_the_same_dataset(tmp_path, capsys, variant):
    outs = []
    for style in ("std", "readme"):
        root = tmp_path / style / "infrastructure-side"
        write_dair_tree(root, 4, seed=7, variant=variant, key_style=style)
        assert any(k.startswith("label_camera_" + ("std_" if style == "std" else "path")) for k in read(root / "data_info.json")[0])
        assert convert(root, tmp_path / f"out-{style}", capsys)[0] == 0
        outs.append(records(tmp_path / f"out-{style}"))
    assert outs[0] == outs[1]
    assert all(name.startswith(f"dair-v2x-{variant}-") for name in outs[0])


def test_tr_velo_to_cam_extrinsics_give_the_same_dataset(tmp_path, capsys):
    outs = {}
    for style in ("rt", "tr", "mixed"):
        root = tmp_path / style / "infrastructure-side"
        write_dair_tree(root, 4, seed=8, variant="c", extrinsic_style=style)
        assert convert(root, tmp_path / f"out-{style}", capsys)[0] == 0
        outs[style] = records(tmp_path / f"out-{style}")
    assert "Tr_velo_to_cam" in read(tmp_path / "tr/infrastructure-side/calib/virtuallidar_to_camera/000000.json")
    assert outs["rt"] == outs["tr"] == outs["mixed"]


def test_extrinsic_layouts_parse():
    f = Path("calib.json")
    R = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    t = [1.0, 2.0, 3.0]
    m34 = np.hstack([R, np.array(t)[:, None]])
    m44 = np.vstack([m34, [0, 0, 0, 1]])
    for data in ({"rotation": R.tolist(), "translation": [[1.0], [2.0], ["3.0"]]},
                 {"transform": {"rotation": R.reshape(-1).tolist(), "translation": t}},
                 {"Tr_velo_to_cam": m34.tolist()}, {"Tr_velo_to_cam": m34.reshape(-1).tolist()},
                 {"Tr_velo_to_cam": m44.tolist()}):
        ext = dair.parse_extrinsics(data, f)
        np.testing.assert_array_equal(ext.rotation, R)
        np.testing.assert_array_equal(ext.translation, t)
    nearly = dair.parse_extrinsics({"rotation": (R * 1.001).tolist(), "translation": t}, f)
    assert is_rotation(nearly.rotation, 1e-12) and np.abs(nearly.rotation - R).max() < 1e-2
    with pytest.raises(dair.SourceError, match="rotation: not a rotation matrix"):
        dair.parse_extrinsics({"rotation": (R * 1.2).tolist(), "translation": t}, f)
    with pytest.raises(dair.SourceError, match="Tr_velo_to_cam: last row"):
        dair.parse_extrinsics({"Tr_velo_to_cam": (m44 * 2).tolist()}, f)


def test_source_is_detected_or_chosen(tmp_path, capsys):
    coop = tmp_path / "cooperative-vehicle-infrastructure"
    write_dair_tree(coop / "infrastructure-side", 2, variant="c")
    (coop / "vehicle-side").mkdir()
    code, out, _ = convert(coop, tmp_path / "out-c", capsys)  # the DAIR-V2X-C root
    assert code == 0 and "dair-v2x-c" in out
    assert set(records(tmp_path / "out-c")) == {"dair-v2x-c-000000.json", "dair-v2x-c-000001.json"}
    single = tmp_path / "single-infrastructure-side"
    write_dair_tree(single, 2, variant="i")
    assert convert(single, tmp_path / "out-i", capsys)[0] == 0
    assert Dataset.open(tmp_path / "out-i")[0].source == "dair-v2x-i"
    assert convert(single, tmp_path / "out-forced", capsys, "--source", "dair-v2x-c")[0] == 0
    assert Dataset.open(tmp_path / "out-forced")[0].frame_id == "dair-v2x-c-000000"


def test_folder_layout_without_data_info(tmp_path, capsys):
    root = tmp_path / "infrastructure-side"
    write_dair_tree(root, 3, variant="i")
    (root / "data_info.json").unlink()
    assert convert(root, tmp_path / "out", capsys)[0] == 0
    ds = Dataset.open(tmp_path / "out")
    assert ds.frame_ids == ["dair-v2x-i-000000", "dair-v2x-i-000001", "dair-v2x-i-000002"]
    assert [r.group for r in ds] == [None, None, None]
    # a second image of one frame, and an image whose name is no frame id: skips naming the file
    shutil.copy(root / "image/000001.jpg", root / "image/000001.png")
    shutil.copy(root / "image/000002.jpg", root / "image/bad name.jpg")
    code, out, _ = convert(root, tmp_path / "again", capsys)
    assert code == 1 and "000001.png" in out and "already has an image, 000001.jpg" in out
    assert "bad name.jpg" in out and "must be letters, digits" in out
    assert len(Dataset.open(tmp_path / "again")) == 3


def test_image_size_is_read_from_each_image(tmp_path, capsys):
    root = tmp_path / "infrastructure-side"
    write_dair_tree(root, 2, variant="i", image_size=(96, 54))
    (root / "image/000001.jpg").write_bytes(tiny_jpeg((64, 40)))
    assert convert(root, tmp_path / "out", capsys)[0] == 0
    assert [(r.width, r.height) for r in Dataset.open(tmp_path / "out")] == [(96, 54), (64, 40)]


def test_images_folder_elsewhere(tmp_path, capsys):
    root = tmp_path / "infrastructure-side"
    write_dair_tree(root, 2, variant="c")
    shutil.move(root / "image", tmp_path / "infrastructure-side-image")
    code, out, _ = convert(root, tmp_path / "out-missing", capsys)
    assert code == 1 and "missing image" in out
    assert convert(root, tmp_path / "out", capsys, "--images", str(tmp_path / "infrastructure-side-image"))[0] == 0


def test_label_set_choice_and_fallback(tmp_path, capsys):
    root = tmp_path / "infrastructure-side"
    write_dair_tree(root, 3, seed=4, variant="c")
    (root / "label/camera/000002.json").unlink()
    code, out, _ = convert(root, tmp_path / "out-strict-labels", capsys)
    assert code == 1
    assert "label/camera/000002.json: missing (named by" in out and "label_camera_std_path" in out
    code, out, _ = convert(root, tmp_path / "out-fallback", capsys, "--fallback-virtuallidar")
    assert code == 0 and "frames labelled from label/virtuallidar: 1" in out
    ds = Dataset.open(tmp_path / "out-fallback")
    assert {o.source_attributes["label_set"] for o in ds.frame("dair-v2x-c-000002").objects} == {"virtuallidar"}
    assert {o.source_attributes["label_set"] for o in ds.frame("dair-v2x-c-000001").objects} == {"camera"}
    assert convert(root, tmp_path / "out-lidar", capsys, "--label", "virtuallidar")[0] == 0
    assert {o.source_attributes["label_set"] for r in Dataset.open(tmp_path / "out-lidar") for o in r.objects} == {"virtuallidar"}


# ---------------------------------------------------------------------------------------------
# Groups
# ---------------------------------------------------------------------------------------------


def test_groups_dair_v2x_i_are_timestamp_runs(tree_i, converted_i, tmp_path, capsys):
    groups = [r.group for r in Dataset.open(converted_i)]
    assert groups == ["dair-v2x-i-run-000000"] * I_RUN + [f"dair-v2x-i-run-{I_RUN:06d}"] * I_RUN
    assert convert(tree_i, tmp_path / "gap", capsys, "--group-gap", "0.5")[0] == 0  # frames are 1 s apart
    assert len({r.group for r in Dataset.open(tmp_path / "gap")}) == 2 * I_RUN
    assert convert(tree_i, tmp_path / "loc", capsys, "--group-by", "intersection")[0] == 0
    assert [r.group for r in Dataset.open(tmp_path / "loc")] == ["dair-v2x-i-yizhuang06"] * I_RUN + ["dair-v2x-i-yizhuang09"] * I_RUN


def test_groups_dair_v2x_c_are_batches(tmp_path, capsys):
    root = tmp_path / "infrastructure-side"
    write_dair_tree(root, C_BATCH + 2, variant="c", objects=(1, 2))
    assert convert(root, tmp_path / "out", capsys)[0] == 0
    assert [r.group for r in Dataset.open(tmp_path / "out")] == ["dair-v2x-c-batch-0"] * C_BATCH + ["dair-v2x-c-batch-1"] * 2


# ---------------------------------------------------------------------------------------------
# Bad input, --strict, determinism, links
# ---------------------------------------------------------------------------------------------


def _corrupt(root: Path) -> dict[str, str]:
    """Break frames 1-9 in different ways; returns frame key -> text its skip line must contain."""
    expect = {}
    label = read(root / "label/camera/000001.json")
    label[0]["3d_dimensions"]["h"] = "abc"
    (root / "label/camera/000001.json").write_text(json.dumps(label))
    expect["1"] = "label/camera/000001.json: [0].3d_dimensions.h: expected a number, got 'abc'"
    intr = read(root / "calib/camera_intrinsic/000002.json")
    intr["cam_K"] = intr["cam_K"][:8]
    (root / "calib/camera_intrinsic/000002.json").write_text(json.dumps(intr))
    expect["2"] = "calib/camera_intrinsic/000002.json: cam_K: expected 3x3 numbers"
    (root / "calib/virtuallidar_to_camera/000003.json").write_text(json.dumps({"translation": [0, 0, 0]}))
    expect["3"] = "calib/virtuallidar_to_camera/000003.json: rotation: missing"
    (root / "image/000004.jpg").unlink()
    expect["4"] = "image/000004.jpg: missing image"
    (root / "label/camera/000005.json").write_text('[{"type": "Car",')
    expect["5"] = "label/camera/000005.json: line 1 column"
    label = read(root / "label/camera/000006.json")
    box = label[0]["2d_box"]
    box["xmin"], box["xmax"] = box["xmax"] + 1, box["xmin"]
    (root / "label/camera/000006.json").write_text(json.dumps(label))
    expect["6"] = "label/camera/000006.json: [0].2d_box: xmax < xmin"
    info = read(root / "data_info.json")
    del info[7]["image_path"]
    info[8]["image_timestamp"] = "soon"
    (root / "data_info.json").write_text(json.dumps(info))
    expect["7"] = "data_info.json: [7].image_path: missing"
    expect["8"] = "data_info.json: [8].image_timestamp: expected microseconds"
    ext = read(root / "calib/virtuallidar_to_camera/000009.json")
    ext["rotation"] = (np.array(ext["rotation"]) * 1.5).tolist()
    (root / "calib/virtuallidar_to_camera/000009.json").write_text(json.dumps(ext))
    expect["9"] = "calib/virtuallidar_to_camera/000009.json: rotation: not a rotation matrix"
    return expect


def test_bad_input_is_skipped_and_named(tmp_path, capsys):
    root = tmp_path / "infrastructure-side"
    write_dair_tree(root, 12, seed=1, variant="i")
    expect = _corrupt(root)
    code, out, _ = convert(root, tmp_path / "out", capsys)
    assert code == 1
    skipped = [line for line in out.splitlines() if line.strip().startswith("skipped:")]
    assert len(skipped) == len(expect)
    for text in expect.values():
        assert any(text in line for line in skipped), (text, skipped)
    ds = Dataset.open(tmp_path / "out")
    assert ds.frame_ids == ["dair-v2x-i-000000", "dair-v2x-i-000010", "dair-v2x-i-000011"]
    assert sorted(p.name for p in (tmp_path / "out/images").iterdir()) == [f"{f}.jpg" for f in ds.frame_ids]


def test_strict_stops_at_the_first_bad_frame(tmp_path, capsys):
    root = tmp_path / "infrastructure-side"
    write_dair_tree(root, 12, seed=1, variant="i")
    expect = _corrupt(root)
    code, _, err = convert(root, tmp_path / "out", capsys, "--strict")
    assert code == 1
    assert expect["1"] in err and "Traceback" not in err
    assert not (tmp_path / "out/manifest.json").exists()


def test_reruns_are_byte_identical_and_images_are_linked(tree_i, converted_i, tmp_path, capsys):
    again = tmp_path / "again"
    assert convert(tree_i, again, capsys)[0] == 0
    assert records(again) == records(converted_i)
    assert (again / "manifest.json").read_bytes() == (converted_i / "manifest.json").read_bytes()
    before = records(again)
    assert convert(tree_i, again, capsys)[0] == 0  # into the same folder: the same bytes
    assert records(again) == before
    image = again / "images/dair-v2x-i-000003.jpg"
    assert os.stat(image).st_ino == os.stat(tree_i / "image/000003.jpg").st_ino
    assert convert(tree_i, tmp_path / "copied", capsys, "--link", "copy")[0] == 0
    copied = tmp_path / "copied/images/dair-v2x-i-000003.jpg"
    assert os.stat(copied).st_ino != os.stat(tree_i / "image/000003.jpg").st_ino
    assert copied.read_bytes() == image.read_bytes()


def test_parallel_workers_give_the_same_dataset(tmp_path, capsys):
    root = tmp_path / "infrastructure-side"
    write_dair_tree(root, 70, seed=9, variant="c", objects=(1, 3))  # enough frames for run_conversion to fork
    assert convert(root, tmp_path / "serial", capsys)[0] == 0
    code = main(["convert", "dair", str(root), "--out", str(tmp_path / "parallel"), "--workers", "2"])
    capsys.readouterr()
    assert code == 0
    assert records(tmp_path / "serial") == records(tmp_path / "parallel")


def test_fixture_is_deterministic_per_frame(tmp_path):
    a = write_dair_tree(tmp_path / "a", 3, seed=4, variant="c")
    b = write_dair_tree(tmp_path / "b", 5, seed=4, variant="c")
    for key in a.keys:
        for sub in ("label/camera", "label/virtuallidar", "calib/virtuallidar_to_camera", "calib/camera_intrinsic"):
            assert (a.root / sub / f"{key}.json").read_bytes() == (b.root / sub / f"{key}.json").read_bytes()
    with Image.open(a.root / "image/000000.jpg") as im:
        assert im.size == (96, 54)


# ---------------------------------------------------------------------------------------------
# The batch path (make_objects) against the one-object-at-a-time reference (make_object)
# ---------------------------------------------------------------------------------------------


def test_batch_objects_equal_one_at_a_time(tree_i):
    """make_objects, which the converter uses, gives records identical to make_object's for the
    fixture's objects plus random ones anywhere around the camera (behind it, outside the image,
    cut by its edge), also under a large image where most objects lie wholly inside."""
    rng = np.random.default_rng(11)
    kinds = {"inside": 0, "cut": 0, "left out": 0, "behind": 0}
    for label_file in sorted((tree_i / "label" / "camera").glob("*.json")):
        key = label_file.stem
        K = dair.parse_intrinsics(read(tree_i / "calib" / "camera_intrinsic" / f"{key}.json"), label_file)
        ext = dair.parse_extrinsics(read(tree_i / "calib" / "virtuallidar_to_camera" / f"{key}.json"), label_file)
        objects = dair.parse_label(read(label_file), label_file).objects
        extra = [dair.LabelObject(index=len(objects) + j, category="car",
                                  center=rng.uniform([-30, -40, -8], [60, 40, 3]), lwh=rng.uniform(0.3, 12.0, 3),
                                  yaw=float(rng.uniform(-4, 4)), box2d=np.array([0.0, 0.0, 5.0, 5.0]),
                                  occlusion_level=int(rng.integers(0, 4)), attributes={"type": "Car"})
                 for j in range(30)]
        for width, height in ((96, 54), (1920, 1080)):
            everything = objects + extra
            batch = dair.make_objects(everything, K, ext, width, height, "camera")
            assert len(batch) == len(everything)
            for o, got in zip(everything, batch):
                want = dair.make_object(o, K, ext, width, height, "camera")
                assert (want is None) == (got is None)
                if want is None:
                    kinds["left out"] += 1
                    continue
                assert json.dumps(got.to_dict()) == json.dumps(want.to_dict())
                kinds["behind" if want.behind_camera.any() else "inside" if want.truncation == 0 else "cut"] += 1
    assert min(kinds.values()) >= 10, kinds
    assert dair.make_objects([], K, ext, 96, 54, "camera") == []


def test_a_calibration_not_quite_orthonormal_maps_centres_as_calibrated_and_axes_as_a_rotation(tmp_path):
    # R scaled by 1.02 passes the tolerance; its nearest rotation would move a car 60 m away by 1.2 m
    c, s = math.cos(0.3), math.sin(0.3)
    level = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])  # LiDAR x forward -> camera z
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    rotation, t = 1.02 * tilt @ level, np.array([0.1, 5.0, 0.2])
    ext = dair.parse_extrinsics({"rotation": rotation.tolist(), "translation": t.tolist()}, tmp_path / "calib.json")
    obj = dair.LabelObject(0, "car", np.array([60.0, 2.0, -4.0]), np.array([4.5, 1.8, 1.5]), 0.4,
                           np.array([0.0, 0.0, 10.0, 10.0]), 0, {})
    K = np.array([[2100.0, 0.0, 960.0], [0.0, 2100.0, 540.0], [0.0, 0.0, 1.0]])
    rec = dair.make_objects([obj], K, ext, 1920, 1080, "camera")[0]
    np.testing.assert_allclose(rec.box.center, rotation @ obj.center + t, atol=1e-9)  # as calibrated
    assert is_rotation(rec.box.rotation) and not np.allclose(rec.box.center, ext.rotation @ obj.center + t, atol=0.5)
    assert rec.to_dict() == dair.make_object(obj, K, ext, 1920, 1080, "camera").to_dict()  # batch = reference


def test_an_image_whose_header_claims_too_many_pixels_is_a_skip_not_a_crash(tmp_path, monkeypatch):
    from PIL import Image as PILImage

    from omnigen.converters import kitti
    from omnigen.converters.common import SourceError

    path = tmp_path / "big.png"
    PILImage.new("RGB", (64, 48)).save(path)
    monkeypatch.setattr(PILImage, "MAX_IMAGE_PIXELS", 100)  # 64 x 48 is now a decompression bomb
    with pytest.raises(SourceError, match="big.png.*unreadable image"):
        dair.read_image_size(path)
    with pytest.raises(SourceError, match="big.png.*unreadable image"):
        kitti.image_size(path, str(path))
