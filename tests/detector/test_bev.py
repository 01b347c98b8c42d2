"""The calibration-free BEV head: right angles and centres on synthetic frames built with
omnigen.geometry (a pitched pinhole camera looking at boxes on a flat ground), the degenerate
same-heading case, the folding guard, ridge placement of 2D-only boxes and `omnigen bev` itself.

Accuracy is measured against the true ground-plane coordinates after a best-fit similarity
(Umeyama, with scale, reflection NOT allowed: the head fixes the handedness from the contract's
corner order, so a mirrored BEV is an error these tests must catch).
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np
import pytest

from omnigen.detector.bev.homography import (DEGENERATE_SPREAD_DEG, apply_homography, class_aspect, fit_ridge, rectify,
                          right_angle_error_deg)
from omnigen.detector.bev.synthetic import SyntheticFrame, centre_error_pct, synthetic_frame, umeyama

def test_exact_keypoints_give_right_angles_and_centres():
    rng = np.random.default_rng(11)
    for _ in range(8):
        f = synthetic_frame(rng)
        res = rectify(f.pixels, f.classes)
        assert not res.degenerate and not res.folded
        assert res.angle_error_deg.max() < 0.5, res.angle_error_deg
        assert centre_error_pct(res.footprints, f.world) < 1.0
        # the frame is (right, forward): no reflection, and the scale is near metres from the priors
        s, r, _ = umeyama(res.footprints.reshape(-1, 2), f.world.reshape(-1, 2))
        assert np.linalg.det(r) > 0 and 0.8 < s < 1.25
        assert r[0, 0] > 0.999  # forward is forward: no rotation left beyond the similarity's noise


def test_two_pixel_noise_stays_within_three_degrees():
    rng = np.random.default_rng(12)
    errors, centres = [], []
    for _ in range(12):
        f = synthetic_frame(rng)
        res = rectify(f.pixels + rng.normal(0, 2.0, f.pixels.shape), f.classes)
        assert not res.folded
        # the rectification's accuracy: the homography found from noisy corners, applied to the true
        # ones (noisy corners themselves are not rectangles under any homography)
        exact = apply_homography(res.homography, f.pixels)
        errors.append(np.median(right_angle_error_deg(exact)))
        centres.append(centre_error_pct(exact, f.world))
    assert np.median(errors) < 3.0, errors
    assert np.median(centres) < 3.0, centres


def test_homography_maps_the_keypoints_it_reports():
    f = synthetic_frame(np.random.default_rng(3))
    res = rectify(f.pixels, f.classes)
    np.testing.assert_allclose(apply_homography(res.homography, f.pixels), res.footprints, atol=1e-9)
    assert math.isclose(np.linalg.norm(res.homography), 1.0)
    assert res.iterations > 0


def test_same_heading_is_flagged_and_settled_by_the_prior():
    rng = np.random.default_rng(5)
    f = synthetic_frame(rng, n=5, same_heading=True, classes=("car",))
    res = rectify(f.pixels, f.classes)
    assert res.degenerate
    assert res.angle_error_deg.max() < 0.5
    lengths = np.linalg.norm(res.footprints[:, 1] - res.footprints[:, 2], axis=1)
    widths = np.linalg.norm(res.footprints[:, 0] - res.footprints[:, 1], axis=1)
    true_aspect = np.linalg.norm(f.world[:, 1] - f.world[:, 2], axis=1) / np.linalg.norm(f.world[:, 0] - f.world[:, 1], axis=1)
    # the unobservable stretch is set by the prior (4.2 / 1.8), not left wherever the start put it
    assert abs(np.median(lengths / widths) - class_aspect("car")) < 0.1 * class_aspect("car")
    assert np.all(np.abs(lengths / widths - true_aspect) < 0.15 * true_aspect)


def test_a_single_footprint_is_degenerate_and_takes_the_prior_aspect():
    f = synthetic_frame(np.random.default_rng(9), n=1, classes=("truck",))
    res = rectify(f.pixels, f.classes)
    assert res.degenerate and res.angle_error_deg.max() < 0.5
    aspect = np.linalg.norm(res.footprints[0, 1] - res.footprints[0, 2]) / np.linalg.norm(res.footprints[0, 0] - res.footprints[0, 1])
    assert abs(aspect - class_aspect("truck")) < 0.02 * class_aspect("truck")


def test_varied_headings_are_not_flagged():
    from omnigen.detector.bev.homography import heading_spread_deg

    f = synthetic_frame(np.random.default_rng(6), n=4)
    res = rectify(f.pixels, f.classes)
    assert not res.degenerate
    assert heading_spread_deg(res.footprints) > DEGENERATE_SPREAD_DEG


def test_folding_guard_keeps_every_point_before_the_vanishing_line():
    """A far, small instance with a few pixels of error gives a DLT start whose vanishing line cuts
    through the near footprints; the head must pull it back and end unfolded and right-angled."""
    rng = np.random.default_rng(8)
    f = synthetic_frame(rng, n=6)
    from omnigen.detector.bev.homography import signed_areas

    far = int(np.argmin(np.abs(signed_areas(f.pixels))))
    bent = f.pixels.copy()
    # a bad keypoint pair: pinch the far footprint's two lowest corners together, so that its sides
    # converge just below it and its own vanishing line runs through the footprints nearer the camera
    low = np.argsort(bent[far, :, 1])[2:]
    mid = bent[far, low].mean(axis=0)
    bent[far, low] = mid + 0.15 * (bent[far, low] - mid)
    from omnigen.detector.bev.homography import _canonical_rectangle, dlt_homography, hartley_normalisation

    T = hartley_normalisation(bent.reshape(-1, 2))
    pts = apply_homography(T, bent)
    Hn = dlt_homography(pts[far], _canonical_rectangle(class_aspect(f.classes[far])))
    w_naive = 1.0 + pts.reshape(-1, 2) @ (Hn[2, :2] / Hn[2, 2])
    assert (w_naive <= 0).any(), "the case must be one where the naive start folds"
    res = rectify(bent, f.classes, init_instance=far)
    assert not res.folded
    w = bent.reshape(-1, 2) @ res.homography[2, :2] + res.homography[2, 2]
    assert (w > 0).all()
    others = np.arange(len(bent)) != far
    assert np.median(res.angle_error_deg[others]) < 1.0


def test_ridge_places_2d_only_boxes_near_their_true_centres():
    rng = np.random.default_rng(21)
    f = synthetic_frame(rng, n=14, classes=("car",))
    res = rectify(f.pixels[:10], f.classes[:10])
    ridge = fit_ridge(f.boxes_xywh[:10], res.centres)
    placed = ridge(f.boxes_xywh[10:])
    # compare in the head's own BEV: where the rectification puts the held-out boxes' true footprints
    truth = apply_homography(res.homography, f.pixels[10:]).mean(axis=1)
    span = np.linalg.norm(np.ptp(res.footprints.reshape(-1, 2), axis=0))
    err = np.linalg.norm(placed - truth, axis=1) / span
    assert np.median(err) < 0.15, err  # the ridge map is linear in phi: a coarse placement (docs/bev.md)
    # and lambda matters: a huge one collapses every box onto the mean centre
    far_off = fit_ridge(f.boxes_xywh[:10], res.centres, lam=1e9)(f.boxes_xywh[10:])
    assert np.median(np.linalg.norm(far_off - truth, axis=1) / span) > np.median(err)


def test_bad_input_is_refused():
    with pytest.raises(ValueError, match="N, 4, 2"):
        rectify(np.zeros((2, 3, 2)))
    with pytest.raises(ValueError, match="finite"):
        rectify(np.full((1, 4, 2), np.nan))


def test_fake_dataset_frames_rectify_against_their_ground_plane():
    """Frames from omnigen.fakes (the renderer's stand-in): keypoints from the records, truth from
    the records' ground planes (omnigen.draw.footprints)."""
    from omnigen.draw import footprints
    from omnigen.fakes import random_frame

    checked = 0
    for index in range(6):
        rec = random_frame(seed=4, index=index, view="infrastructure", n_objects=8, width=1280, height=720)
        objs = [i for i, o in enumerate(rec.objects) if not o.behind_camera[4:8].any()]
        if len(objs) < 3:
            continue
        ground = np.stack([rec.objects[i].keypoints[4:8] for i in objs])
        res = rectify(ground, [rec.objects[i].category for i in objs])
        truth = footprints(rec)[objs]
        assert res.angle_error_deg.max() < 0.5
        assert centre_error_pct(res.footprints, truth) < 1.0
        checked += 1
    assert checked >= 3


def _write_predictions(tmp_path, frame: SyntheticFrame, n_2d: int) -> tuple:
    preds = []
    for j in range(len(frame.pixels)):
        kp = np.zeros((8, 3))
        kp[4:8, :2] = frame.pixels[j]
        kp[:, 2] = 2.0
        kp[:4, :2] = frame.pixels[j] - [0, 30]  # top corners: unused by the head
        entry = {"image_id": 7, "category_id": 1, "bbox": frame.boxes_xywh[j].tolist(), "score": 0.9}
        if j < len(frame.pixels) - n_2d:
            entry["keypoints"] = kp.ravel().tolist()
        preds.append(entry)
    path = tmp_path / "preds.json"
    path.write_text(json.dumps(preds))
    return path, preds


def _run_bev(argv: list[str]) -> int:
    from omnigen.detector import bev_command

    parser = argparse.ArgumentParser()
    bev_command.add_arguments(parser)
    return bev_command.run(parser.parse_args(argv))


def test_bev_command_writes_json_and_picture(tmp_path):
    from PIL import Image

    f = synthetic_frame(np.random.default_rng(31), n=8, classes=("car",))
    path, _ = _write_predictions(tmp_path, f, n_2d=2)
    assert _run_bev([str(path), "--out", str(tmp_path / "bev")]) == 0
    rec = json.loads((tmp_path / "bev" / "7.json").read_text())
    Hm = np.array(rec["homography"])
    fp = np.array([d["footprint"] for d in rec["detections"]])
    assert fp.shape == (6, 4, 2) and len(rec["placed_2d"]) == 2
    np.testing.assert_allclose(apply_homography(Hm, f.pixels[:6]), fp, atol=1e-6)
    assert centre_error_pct(fp, f.world[:6]) < 1.0
    placed = np.array([d["centre"] for d in rec["placed_2d"]])
    truth = apply_homography(Hm, f.pixels[6:]).mean(axis=1)
    extent = np.linalg.norm(np.ptp(fp.reshape(-1, 2), axis=0))
    assert np.isfinite(placed).all() and np.linalg.norm(placed - truth, axis=1).max() < 0.3 * extent
    via_h = np.array([d["centre_bottom_through_h"] for d in rec["placed_2d"]])
    assert np.linalg.norm(via_h - truth, axis=1).max() < 0.15 * extent
    with Image.open(tmp_path / "bev" / "7.png") as im:
        assert im.width > im.height > 300  # image panel and BEV side by side


def test_bev_command_names_file_and_field_on_bad_input(tmp_path):
    f = synthetic_frame(np.random.default_rng(32), n=3, classes=("car",))
    path, preds = _write_predictions(tmp_path, f, n_2d=0)
    preds[1]["keypoints"] = preds[1]["keypoints"][:20]
    path.write_text(json.dumps(preds))
    with pytest.raises(ValueError, match=r"preds\.json: entry 1: field 'keypoints'"):
        _run_bev([str(path), "--out", str(tmp_path / "o")])
    preds[1]["keypoints"] = preds[0]["keypoints"]
    preds[2]["category_id"] = 99
    path.write_text(json.dumps(preds))
    with pytest.raises(ValueError, match=r"entry 2: field 'category_id'"):
        _run_bev([str(path), "--out", str(tmp_path / "o")])
    path.write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        _run_bev([str(path), "--out", str(tmp_path / "o")])
    assert not (tmp_path / "o").exists()


def test_wild_corners_of_a_poor_detector_never_crash():
    """Corners of an undertrained model (random quads, crossed, tiny, far apart) give a result or
    a clear error, never an overflow."""
    rng = np.random.default_rng(5)
    for _ in range(10):
        quads = rng.uniform(0, 320, (int(rng.integers(1, 12)), 4, 2))
        quads[: len(quads) // 3] *= rng.uniform(1e-3, 1e3)
        try:
            res = rectify(quads)
        except ValueError:
            continue
        assert np.isfinite(res.homography).all()


def test_the_bev_caption_wraps_whole_words_to_the_panel():
    """A small BEV panel cut its caption mid-word ("aspec"): the words now wrap to its width."""
    from PIL import Image, ImageDraw

    from omnigen.detector.bev.draw import wrap_words
    from omnigen.draw import font

    draw = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    words = ["BEV (no calibration),", "grid 5 m", "(class-prior scale),", "one heading:", "aspect from prior"]
    lines = wrap_words(draw, words, font(11), 200)
    assert " ".join(lines) == " ".join(words) and len(lines) > 1
    assert all(draw.textlength(line, font=font(11)) <= 200 for line in lines)
    assert wrap_words(draw, words, font(11), 10_000) == [" ".join(words)]


def test_bev_finds_the_pictures_predict_read_by_their_file_names(tmp_path, capsys):
    """`omnigen predict` numbers its images and names each detection's file: bev looked for
    <image_id>.png and drew every picture on grey ("[no image]") without a word on the console."""
    from PIL import Image

    f = synthetic_frame(np.random.default_rng(33), n=4, classes=("car",))
    path, preds = _write_predictions(tmp_path, f, n_2d=0)
    for entry in preds:
        entry["image_id"], entry["file_name"] = 1, str(tmp_path / "elsewhere" / "frame-a.jpg")
    path.write_text(json.dumps(preds + [dict(preds[0], image_id=2, file_name="missing.png")]))
    images = tmp_path / "images"
    images.mkdir()
    Image.new("RGB", (1280, 720), (200, 30, 30)).save(images / "frame-a.jpg")
    code = _run_bev([str(path), "--out", str(tmp_path / "bev"), "--images", str(images)])
    with Image.open(tmp_path / "bev" / "1.png") as im:
        assert (np.asarray(im.convert("RGB"))[:, :, 0] > 150).mean() > 0.2  # drawn over its own red picture
    err = capsys.readouterr().err
    assert "image 2: no missing.png in" in err and "frame-a" not in err
    assert code == 1  # a picture asked for and not found is reported
