"""Metric 3D lifting (detector/bev/lift.py) and the calibration-sensitivity command's parts."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest

from omnigen.converters.kitti import parse_labels
from omnigen.detector.calib_command import (PERTURBATIONS, Perturbation, add_arguments, lift_frames, load_predictions,
                                    representative_fine_classes, run, sensitivity)
from omnigen.detector.bev.lift import (DimensionPriors, LiftedBoxes, fit_dimension_priors, ground_adherence_deg,
                           lift_keypoints, to_kitti_lines)
from omnigen.formats.coco import to_coco
from omnigen.conventions import FINE_CLASSES
from omnigen.fakes import write_fake_dataset
from omnigen.formats.kitti import box_from_kitti
from omnigen.geometry import Box3D, plane_from_height_pitch, project_points, rot_x, rot_z
from omnigen.priors import PRIORS
from omnigen.splits import write_split
from omnigen.taxonomy import load_taxonomy

K_EGO = np.array([[721.5, 0.0, 609.6], [0.0, 721.5, 172.9], [0.0, 0.0, 1.0]])
K_POLE = np.array([[2100.0, 0.0, 960.0], [0.0, 2100.0, 540.0], [0.0, 0.0, 1.0]])
LEVEL = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # world (x right, y forward, z up) -> level camera


def ego_boxes() -> list[Box3D]:
    return [box_from_kitti(1.5, 1.7, 4.1, 2.5, 1.65, 14.0, 0.4), box_from_kitti(1.8, 0.6, 0.7, -3.0, 1.7, 22.0, -2.2),
            box_from_kitti(3.1, 2.5, 9.0, 6.0, 1.6, 38.0, 1.3)]


def pole_camera(pitch_deg: float = 30.0, height: float = 7.0) -> tuple[np.ndarray, np.ndarray]:
    """World -> camera rotation of a camera `height` up and pitched down, and its ground plane."""
    pitch = math.radians(pitch_deg)
    plane = plane_from_height_pitch(height, pitch)
    return rot_x(pitch) @ LEVEL, np.array([*plane.normal, plane.offset])


def pole_boxes(world_to_cam: np.ndarray, height: float = 7.0) -> list[Box3D]:
    out = []
    for (x, y, yaw), dims in zip([(2.0, 14.0, 0.3), (-4.0, 25.0, 2.0), (6.0, 18.0, -1.1)],
                                 [(4.2, 1.8, 1.5), (0.6, 0.6, 1.75), (8.0, 2.5, 3.2)]):
        centre = np.array([x, y, -height + dims[2] / 2])
        out.append(Box3D(world_to_cam @ centre, dims, world_to_cam @ rot_z(yaw)))
    return out


def keypoints_of(boxes: list[Box3D], K: np.ndarray) -> np.ndarray:
    return np.stack([project_points(K, b.corners())[0] for b in boxes])


def rotation_error_deg(a: np.ndarray, b: np.ndarray) -> float:
    c = (np.trace(a.T @ b) - 1.0) / 2.0
    return math.degrees(math.acos(np.clip(c, -1.0, 1.0)))


def lifted_of(boxes: list[Box3D]) -> LiftedBoxes:
    n = len(boxes)
    return LiftedBoxes(R=np.stack([b.rotation for b in boxes]), t=np.stack([b.center for b in boxes]),
                       dims=np.stack([b.dims for b in boxes]), ok=np.ones(n, bool), reproj_px=np.zeros(n))


@pytest.mark.parametrize("view", ["ego", "pole"])
def test_exact_keypoints_and_true_dims_recover_the_box(view):
    if view == "ego":
        boxes, K = ego_boxes(), K_EGO
    else:
        boxes, K = pole_boxes(pole_camera()[0]), K_POLE
    lifted = lift_keypoints(keypoints_of(boxes, K), np.stack([b.dims for b in boxes]), K)
    assert lifted.ok.all()
    for i, b in enumerate(boxes):
        assert np.linalg.norm(lifted.t[i] - b.center) < 0.01
        assert rotation_error_deg(lifted.R[i], b.rotation) < 0.1
    assert (lifted.reproj_px < 1e-3).all()


def test_prior_dims_move_the_centre_but_keep_the_heading():
    boxes = ego_boxes()
    true_dims = np.stack([b.dims for b in boxes])
    lifted = lift_keypoints(keypoints_of(boxes, K_EGO), true_dims * [1.1, 0.93, 1.05], K_EGO)
    assert lifted.ok.all()
    centre_err = np.linalg.norm(lifted.t - np.stack([b.center for b in boxes]), axis=1)
    assert (centre_err > 0.05).any()  # wrong sizes cost metric accuracy...
    for i, b in enumerate(boxes):
        cos = float(lifted.R[i][:, 0] @ b.forward)
        assert math.degrees(math.acos(min(cos, 1.0))) < 3.0  # ...but not the heading
    assert (lifted.reproj_px > 0).all()


def test_too_few_corners_or_behind_camera_is_not_ok():
    boxes = ego_boxes()
    kp = keypoints_of(boxes, K_EGO)
    valid = np.ones((3, 8), bool)
    valid[0, :5] = False  # 3 corners left
    kp[1, :] = np.nan
    lifted = lift_keypoints(kp, np.stack([b.dims for b in boxes]), K_EGO, valid=valid)
    assert lifted.ok.tolist() == [False, False, True]
    assert np.isnan(lifted.t[:2]).all() and np.isnan(ground_adherence_deg(lifted, [0, -1, 0, 1.65])[:2]).all()


def test_ground_adherence_of_true_and_tilted_boxes():
    world_to_cam, plane = pole_camera()
    boxes = pole_boxes(world_to_cam)
    assert np.allclose(ground_adherence_deg(lifted_of(boxes), plane), 0.0, atol=1e-6)
    tilt = math.radians(5.0)
    tilted = [Box3D(b.center, b.dims, b.rotation @ rot_x(tilt)) for b in boxes]
    # About its x axis: the two edges along y (4-5, 6-7) leave the ground by 5 deg, the two along x stay.
    expected = (5.0 + 0.0 + 5.0 + 0.0) / 4
    assert np.allclose(ground_adherence_deg(lifted_of(tilted), plane), expected, atol=1e-6)
    # ...and the lift of the tilted boxes' exact keypoints sees the same tilt.
    lifted = lift_keypoints(keypoints_of(tilted, K_POLE), np.stack([b.dims for b in tilted]), K_POLE)
    assert np.allclose(ground_adherence_deg(lifted, plane), expected, atol=0.05)
    # An unnormalised plane gives the same angles.
    assert np.allclose(ground_adherence_deg(lifted, plane * 3.0), expected, atol=0.05)


@pytest.fixture(scope="module")
def fake_ds(tmp_path_factory):
    root = tmp_path_factory.mktemp("lift") / "ds"
    ds = write_fake_dataset(root, 9, objects_per_frame=6, seed=3, source="synthetic", images=False)
    ids = ds.frame_ids
    write_split(root, "train", ids[3:])
    write_split(root, "test", ids[:3])
    return ds


def test_priors_are_the_training_medians(fake_ds):
    train = fake_ds.frame_ids[3:]
    priors = fit_dimension_priors(fake_ds, train)
    by_class: dict[str, list] = {}
    for f in train:  # an independent path: the records, not the object table
        for o in fake_ds.frame(f).objects:
            by_class.setdefault(o.category, []).append(o.box.dims)
    assert by_class
    for name in FINE_CLASSES:
        if name in by_class:
            assert np.allclose(priors.dims[name], np.median(by_class[name], axis=0))
            assert priors.counts[name] == len(by_class[name])
        else:
            assert priors.dims[name] == tuple(PRIORS[name].mean) and priors.counts[name] == 0
    assert np.allclose(priors.dims_for(["car", "pedestrian"]), [priors.dims["car"], priors.dims["pedestrian"]])
    again = DimensionPriors.from_dict(json.loads(json.dumps(priors.to_dict())))
    assert again == priors
    empty = fit_dimension_priors(fake_ds, [])
    assert empty.dims["car"] == tuple(PRIORS["car"].mean)
    with pytest.raises(KeyError, match="lorry"):
        priors.dims_for(["lorry"])


@pytest.mark.parametrize("view", ["ego", "pole"])
def test_kitti_lines_round_trip_through_the_kitti_parser(view):
    boxes = ego_boxes() if view == "ego" else pole_boxes(pole_camera()[0])
    lifted = lifted_of(boxes)
    lifted.ok[1] = False
    names = ["car", "pedestrian", "truck"]
    boxes2d = np.array([[10.0, 20.0, 110.0, 90.0]] * 3)
    lines = to_kitti_lines(lifted, names, boxes2d, truncated=np.zeros(3), occluded=np.zeros(3, int))
    labels = parse_labels("\n".join(lines), "lifted.txt")
    assert [lab.type for lab in labels] == ["Car", "Truck"]
    for lab, b in zip(labels, [boxes[0], boxes[2]]):
        back = box_from_kitti(*lab.hwl, *lab.location, lab.rotation_y)
        assert np.allclose(back.center, b.center, atol=1e-9)
        assert np.allclose(back.dims, b.dims)
        assert lab.bbox == (10.0, 20.0, 110.0, 90.0)
        if view == "ego":
            assert np.allclose(back.rotation, b.rotation, atol=1e-9)
        else:  # pitched: the heading in the camera's x-z plane survives, the tilt does not
            f = b.forward
            assert math.isclose(lab.rotation_y, math.atan2(-f[2], f[0]), abs_tol=1e-9)
    scored = to_kitti_lines(lifted, names, boxes2d, scores=np.array([0.9, 0.8, 0.7]))
    assert len(scored[0].split()) == 16 and scored[0].split()[-1] == "0.9" and scored[0].split()[1] == "-1.0"


def test_focal_x09_scales_the_lifted_depth_by_09():
    boxes = ego_boxes()
    kp = keypoints_of(boxes, K_EGO)
    dims = np.stack([b.dims for b in boxes])
    ref = lift_keypoints(kp, dims, K_EGO)
    short = lift_keypoints(kp, dims, Perturbation("f", focal_scale=0.9).apply(K_EGO))
    ratio = short.t[:, 2] / ref.t[:, 2]
    assert np.allclose(ratio, 0.9, atol=0.01)
    shifted = lift_keypoints(kp, dims, Perturbation("cx", cx_shift=50.0).apply(K_EGO))
    assert np.allclose(shifted.t[:, 2] / ref.t[:, 2], 1.0, atol=0.02)  # a shift moves boxes sideways...
    assert (shifted.t[:, 0] < ref.t[:, 0] - 0.5).all()  # ...to the left, by ~ 50 px * z / f


def test_perturbations_change_only_what_they_name():
    names = [p.name for p in PERTURBATIONS]
    assert names[0] == "reference" and np.array_equal(PERTURBATIONS[0].apply(K_EGO), K_EGO)
    K = Perturbation("x", focal_scale=0.95, cx_shift=50.0).apply(K_EGO)
    assert K[0, 0] == pytest.approx(0.95 * 721.5) and K[1, 1] == pytest.approx(0.95 * 721.5)
    assert K[0, 2] == pytest.approx(659.6) and K[1, 2] == K_EGO[1, 2]


def gt_predictions(ds, frames: list[int]) -> list[dict]:
    """The ground truth's own keypoints as COCO-results detections (score 1)."""
    coco = to_coco(ds)
    keep = {f + 1 for f in frames}
    return [{"image_id": a["image_id"], "category_id": a["category_id"], "keypoints": a["keypoints"],
             "bbox": a["bbox"], "score": 1.0} for a in coco["annotations"] if a["image_id"] in keep]


def test_lift_frames_from_coco_results(fake_ds, tmp_path):
    frames = list(range(3))
    dets = gt_predictions(fake_ds, frames)
    path = tmp_path / "pred.json"
    path.write_text(json.dumps(dets))
    priors = fit_dimension_priors(fake_ds, fake_ds.frame_ids[3:])
    preds = load_predictions(path, fake_ds, representative_fine_classes(load_taxonomy("fine"), priors))
    assert sum(len(p.scores) for p in preds.values()) == len(dets)
    summary = lift_frames(fake_ds, frames, preds, priors, PERTURBATIONS[0])
    shorter = lift_frames(fake_ds, frames, preds, priors, PERTURBATIONS[3])
    ok = np.isfinite(summary.depth) & np.isfinite(shorter.depth)
    assert ok.mean() > 0.5
    assert np.median(shorter.depth[ok] / summary.depth[ok]) == pytest.approx(0.9, abs=0.02)
    assert sum(len(v) for v in summary.lines.values()) == int(np.isfinite(summary.depth).sum())
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps([{**dets[0], "image_id": 999}]))
    with pytest.raises(ValueError, match="image_id"):
        load_predictions(bad, fake_ds, list(FINE_CLASSES))


def test_sensitivity_writes_folders_and_reports_without_evaluator(fake_ds, tmp_path):
    frames = [0, 1, 2]
    path = tmp_path / "pred.json"
    path.write_text(json.dumps(gt_predictions(fake_ds, frames)))
    priors = fit_dimension_priors(fake_ds, fake_ds.frame_ids[3:])
    preds = load_predictions(path, fake_ds, list(FINE_CLASSES))
    seen = []
    results = sensitivity(fake_ds, frames, preds, priors, lambda g, p: seen.append((g, p)) or {"AP40": {}},
                          tmp_path / "work")
    assert len(results) == len(PERTURBATIONS) == len(seen)
    assert results[0]["median_depth_ratio"] == pytest.approx(1.0)
    assert results[3]["median_depth_ratio"] == pytest.approx(0.9, abs=0.02)
    gt_files = sorted((tmp_path / "work" / "gt").glob("*.txt"))
    assert len(gt_files) == 3 and all(len(list((tmp_path / "work" / f"pred_{k}").glob("*.txt"))) == 3
                                      for k in range(len(PERTURBATIONS)))


def test_command_end_to_end(fake_ds, tmp_path, capsys):
    path = tmp_path / "pred.json"
    path.write_text(json.dumps(gt_predictions(fake_ds, [0, 1, 2])))
    p = argparse.ArgumentParser()
    add_arguments(p)
    out = tmp_path / "calib.json"
    assert run(p.parse_args([str(path), str(fake_ds.root), "--views", "all", "--out", str(out)])) == 0
    report = json.loads(out.read_text())
    assert [r["name"] for r in report["perturbations"]] == [q.name for q in PERTURBATIONS]
    assert all("AP40" in r["kitti"] for r in report["perturbations"])
    assert "calibration sensitivity" in capsys.readouterr().out


def test_exact_lifts_score_in_3d_what_they_score_in_2d(tmp_path):
    """Lifted lines and exported ground truth agree on KITTI's conventions: with exact corners and
    true sizes, every 3D and BEV match the 2D box match does (a sign or offset slip would zero them)."""
    from omnigen.formats.kitti import label_text
    from omnigen.detector.evaluation.kitti_eval import evaluate_folders
    from omnigen.record import FrameRecord, ObjectRecord

    (tmp_path / "gt").mkdir()
    (tmp_path / "pred").mkdir()
    for n in range(4):
        boxes = [box_from_kitti(1.5, 1.7, 4.1, -4.0 + 3.0 * k, 1.65, 10.0 + 6.0 * k + n, 0.5 * n - k)
                 for k in range(3)]
        objects = [ObjectRecord.from_box("car", k + 1, b, K_EGO, 1242, 375, occlusion=None, occlusion_level=0)
                   for k, b in enumerate(boxes)]
        record = FrameRecord(frame_id=f"kitti-{n:06d}", source="kitti", view="ego", image=f"images/{n}.png",
                             width=1242, height=375, K=K_EGO, objects=objects)
        (tmp_path / "gt" / f"{n:06d}.txt").write_text(label_text(record))
        lifted = lift_keypoints(np.stack([o.keypoints for o in objects]), np.stack([b.dims for b in boxes]), K_EGO)
        lines = to_kitti_lines(lifted, ["car"] * 3, np.stack([o.bbox for o in objects]), scores=np.ones(3))
        (tmp_path / "pred" / f"{n:06d}.txt").write_text("".join(f"{line}\n" for line in lines))
    ap = evaluate_folders(tmp_path / "gt", tmp_path / "pred")["AP40"]["Car"]
    assert ap["bbox"][1] > 0
    assert ap["3d"] == pytest.approx(ap["bbox"]) and ap["bev"] == pytest.approx(ap["bbox"])


def test_strided_keypoint_views_lift_like_copies():
    """x, y sliced out of COCO's x, y, v rows is a strided view; the lift must not misread it."""
    boxes = ego_boxes()
    xyv = np.concatenate([keypoints_of(boxes, K_EGO), np.full((3, 8, 1), 2.0)], axis=2)
    lifted = lift_keypoints(xyv[..., :2], np.stack([b.dims for b in boxes]), K_EGO)
    assert lifted.ok.all() and np.allclose(lifted.t, np.stack([b.center for b in boxes]), atol=0.01)
