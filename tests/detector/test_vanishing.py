"""detector/prediction/vanishing.py: the vertical vanishing point from boxes and from an image's line
segments, and the snap that turns predicted vertical edges to it."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from omnigen.detector.prediction.vanishing import (SnapOptions, fit_vertical_vanishing_point, image_vertical_point,
                                        refine_with_segments, snap_vertical, turn_vertical_edges)

W, H = 640, 480


def as_pixels(v: np.ndarray) -> np.ndarray:
    return v[:2] / v[2] * max(W, H) + np.array([(W - 1) / 2, (H - 1) / 2])


def normalised(px: np.ndarray) -> np.ndarray:
    v = np.array([*(px - [(W - 1) / 2, (H - 1) / 2]) / max(W, H), 1.0])
    return v / np.linalg.norm(v)


def aim_error_deg(v: np.ndarray, vp: np.ndarray) -> float:
    """The largest angle, over a grid of image points, between the lines to v and to the pixel vp."""
    grid = np.stack(np.meshgrid(np.linspace(0, W, 5), np.linspace(0, H, 5)), -1).reshape(-1, 2)
    a, b = as_pixels(v) - grid, vp - grid
    cos = np.sum(a * b, 1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1))).max())


def boxes_towards(vp: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """n boxes (n, 8, 2) whose vertical edges lie on lines through the pixel `vp`, bottoms nearer it."""
    top = rng.uniform([100, 80], [540, 300], (n, 1, 2)) + rng.uniform(-20, 20, (n, 4, 2))
    return np.concatenate([top, top + rng.uniform(0.1, 0.3, (n, 1, 1)) * (vp - top)], axis=1)


def test_the_fit_finds_the_point_the_vertical_edges_meet_at_despite_a_wrong_box():
    rng = np.random.default_rng(0)
    vp = np.array([300.0, 1500.0])
    kp = boxes_towards(vp, 12, rng)
    kp[0, 4:] = kp[0, :4] + [[40.0, 5.0]]  # one box whose edges point elsewhere
    v = fit_vertical_vanishing_point(kp, np.ones(12), W, H)
    assert np.allclose(as_pixels(v), vp, atol=15.0)
    assert v[2] > 0  # signed: the motion from the top faces to the bottom ones runs towards it
    # parallel edges (an upright camera): a point at infinity, pointing down the image
    flat = kp[1:].copy()
    flat[:, 4:] = flat[:, :4] + [[0.0, 30.0]]
    v = fit_vertical_vanishing_point(flat, np.ones(11), W, H)
    assert abs(v[2]) < 1e-6 and abs(v[0]) < 1e-6 and v[1] > 0
    with pytest.raises(ValueError, match="no vertical edge"):
        fit_vertical_vanishing_point(np.zeros((2, 8, 2)), np.ones(2), W, H)


def test_turning_the_edges_keeps_their_midpoints_and_lengths_and_aims_them_at_the_point():
    rng = np.random.default_rng(1)
    vp = np.array([250.0, -900.0])
    kp = boxes_towards(vp, 5, rng)
    v = normalised(vp)
    assert np.allclose(turn_vertical_edges(kp, v, W, H), kp, atol=1e-9)  # already aimed: unchanged
    bent = kp.copy()
    bent[:, 4:] += rng.normal(0, 3, (5, 4, 2))
    turned = turn_vertical_edges(bent, v, W, H)
    mid = lambda k: (k[:, :4] + k[:, 4:]) / 2  # noqa: E731
    length = lambda k: np.linalg.norm(k[:, 4:] - k[:, :4], axis=-1)  # noqa: E731
    assert np.allclose(mid(turned), mid(bent)) and np.allclose(length(turned), length(bent))
    e, to_vp = turned[:, 4:] - turned[:, :4], vp - turned[:, :4]
    assert np.allclose(e[..., 0] * to_vp[..., 1] - e[..., 1] * to_vp[..., 0], 0.0, atol=1e-6)
    assert (np.sum(e * (bent[:, 4:] - bent[:, :4]), axis=-1) > 0).all()  # each edge keeps its sense


def city_image(vertical: np.ndarray, horizontal: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A gray image with long dark lines through the pixel `vertical` (12 of them, 'building
    corners') and through `horizontal` (16, 'kerbs and roofs', more of them and as long)."""
    image = np.full((H, W), 170, np.uint8)
    for x in np.linspace(40, 600, 12):
        a = np.array([x, 30.0])
        b = a + 0.35 * (vertical - a)
        cv2.line(image, tuple(int(round(c)) for c in a), tuple(int(round(c)) for c in b), 40, 3)
    for y in np.linspace(60, 440, 16):
        a = np.array([620.0, y])
        b = a + 0.3 * (horizontal - a)
        cv2.line(image, tuple(int(round(c)) for c in a), tuple(int(round(c)) for c in b), 60, 3)
    return np.clip(image + rng.normal(0, 3, image.shape), 0, 255).astype(np.uint8)


def test_the_image_lines_place_the_point_the_boxes_only_roughly_give():
    rng = np.random.default_rng(2)
    vertical, horizontal = np.array([330.0, 1400.0]), np.array([-2500.0, 250.0])
    gray = city_image(vertical, horizontal, rng)
    kp = boxes_towards(vertical, 8, rng)
    kp[:, 4:] += rng.normal(0, 4, (8, 4, 2))  # a model's edges: each some degrees off
    kp[:, 4:] += [[12.0, 0.0]]  # ... and leaning one way together, as a model's errors do
    first = fit_vertical_vanishing_point(kp, np.ones(8), W, H)
    v = image_vertical_point(gray, kp, np.ones(8))
    assert v is not None and v[2] > 0
    assert aim_error_deg(v, vertical) < 1.0 < 2.0 < aim_error_deg(first, vertical)
    # without segments near it the boxes' own point stands
    assert np.allclose(refine_with_segments(first, kp, np.ones(8), np.zeros((0, 4)), W, H), first)
    # too few boxes to fit any point: no point, and the snap leaves the corners as they were
    assert image_vertical_point(gray, kp[:1], np.ones(1)) is None
    assert np.array_equal(snap_vertical(gray, kp[:1], np.ones(1)), kp[:1])
    # boxes scored under the threshold do not fit it either
    assert image_vertical_point(gray, kp, np.full(8, 0.1), SnapOptions(score_thr=0.3)) is None


def test_the_snap_aims_every_detection_at_the_image_point_the_horizontal_lines_do_not_take():
    rng = np.random.default_rng(3)
    vertical, horizontal = np.array([330.0, 1400.0]), np.array([-2500.0, 250.0])
    gray = city_image(vertical, horizontal, rng)
    kp = boxes_towards(vertical, 8, rng)
    kp[:, 4:] += rng.normal(0, 4, (8, 4, 2))
    # two weak detections (under the fit's threshold) are snapped too, and multi-label copies count once
    scores = np.array([0.9, 0.8, 0.8, 0.7, 0.6, 0.5, 0.05, 0.02])
    snapped = snap_vertical(gray, np.concatenate([kp, kp[:3]]), np.concatenate([scores, scores[:3]]))
    e, to_vp = snapped[:, 4:] - snapped[:, :4], vertical - snapped[:, :4]
    sine = np.abs(e[..., 0] * to_vp[..., 1] - e[..., 1] * to_vp[..., 0]) / (
        np.linalg.norm(e, axis=-1) * np.linalg.norm(to_vp, axis=-1))
    assert np.degrees(np.arcsin(sine)).max() < 0.5
    assert np.allclose(snapped[8:], snapped[:3])  # a copy's corners are its original's


def test_prediction_snaps_in_the_letterboxed_input_without_the_padding_border():
    """predict.snap_batch: an image 320 x 200 letterboxed to 320 (60 rows of padding above and
    below, whose border is a long straight edge): the detections' vertical edges end up aimed at
    the image's point, in input pixels, and every other field is kept."""
    import torch

    from omnigen.detector.data.samples import letterbox
    from omnigen.detector.model.outputs import Detections
    from omnigen.detector.prediction.predict import PredictOptions, snap_batch

    rng = np.random.default_rng(4)
    vertical = np.array([160.0, 900.0])  # image pixels of the 320 x 200 original
    image = np.full((200, 320), 170, np.uint8)
    for x in np.linspace(20, 300, 10):
        a = np.array([x, 10.0])
        b = a + 0.15 * (vertical - a)
        cv2.line(image, tuple(int(round(c)) for c in a), tuple(int(round(c)) for c in b), 40, 2)
    boxed, lb = letterbox(np.repeat(image[..., None], 3, axis=2), 320)
    assert lb.pad == (0, 60) and lb.gain == 1.0
    target = vertical + np.array(lb.pad)  # the point in input pixels
    top = rng.uniform([40, 80], [280, 150], (6, 1, 2)) + rng.uniform(-10, 10, (6, 4, 2))
    kp = np.concatenate([top, top + 0.1 * (target - top)], axis=1)
    kp[:, 4:] += rng.normal(0, 2, (6, 4, 2))
    dets = Detections(torch.zeros(6, 4), torch.full((6,), 0.9), torch.zeros(6, dtype=torch.long),
                      torch.from_numpy(np.concatenate([kp, np.ones((6, 8, 1))], axis=2)).float())
    out = snap_batch([boxed], [lb], [dets])[0]
    got = out.keypoints[..., :2].double().numpy()
    e, to_vp = got[:, 4:] - got[:, :4], target - got[:, :4]
    sine = np.abs(e[..., 0] * to_vp[..., 1] - e[..., 1] * to_vp[..., 0]) / (
        np.linalg.norm(e, axis=-1) * np.linalg.norm(to_vp, axis=-1))
    assert np.degrees(np.arcsin(sine)).max() < 0.2
    mid = lambda k: (k[:, :4] + k[:, 4:]) / 2  # noqa: E731
    assert np.allclose(mid(got), mid(kp), atol=1e-3)  # turned in place: the padding's offset undone
    assert torch.equal(out.keypoints[..., 2], dets.keypoints[..., 2]) and out.scores is dets.scores
    with pytest.raises(ValueError, match="vertical"):
        PredictOptions(vertical="both")


def test_a_box_with_a_non_finite_corner_neither_moves_the_point_nor_is_moved():
    rng = np.random.default_rng(5)
    vp = np.array([300.0, 1500.0])
    kp = boxes_towards(vp, 6, rng)
    clean = fit_vertical_vanishing_point(kp, np.ones(6), W, H)
    bad = np.concatenate([kp, kp[:1]])
    bad[-1, 0] = [np.nan, 10.0]
    bad[-1, 5] = [np.inf, 3.0]
    assert np.allclose(fit_vertical_vanishing_point(bad, np.ones(7), W, H), clean)
    turned = turn_vertical_edges(bad, clean, W, H)
    assert np.isfinite(turned[:6]).all()
    assert np.array_equal(turned[-1], bad[-1], equal_nan=True)  # left as it was


def test_prediction_leaves_out_a_far_side_padding_a_pixel_wider_than_the_near_one(monkeypatch):
    """A 640 x 639 image letterboxed to 640: no padding above, one row below. The snap's region
    is the image's own rows, so the padding's edge (a long straight segment) is not among them."""
    import torch

    import omnigen.detector.prediction.vanishing as vanishing
    from omnigen.detector.data.samples import letterbox
    from omnigen.detector.model.outputs import Detections
    from omnigen.detector.prediction.predict import snap_batch

    image = np.full((639, 640, 3), 30, np.uint8)
    boxed, lb = letterbox(image, 640)
    assert lb.pad == (0.0, 0.0) and lb.content == (640, 639) and (boxed[639] != 30).all()
    seen = []
    original = vanishing.snap_vertical

    def spy(gray, kp, scores, opts=vanishing.SnapOptions()):
        seen.append(gray.shape)
        return original(gray, kp, scores, opts)

    monkeypatch.setattr(vanishing, "snap_vertical", spy)
    dets = Detections(torch.zeros(2, 4), torch.ones(2), torch.zeros(2, dtype=torch.long), torch.zeros(2, 8, 3))
    snap_batch([boxed], [lb], [dets])
    assert seen == [(637, 640)]  # rows 0..636: the image less a margin of 2 above the padded row


def test_omnigen_predict_passes_vertical_to_prediction(tmp_path, monkeypatch):
    """`omnigen predict --vertical off` reaches PredictOptions; lines is the default."""
    import argparse

    import cv2 as _cv2

    import omnigen.detector.model.checkpoint as checkpoint
    import omnigen.detector.prediction.predict as predict
    from omnigen.detector import predict_command

    _cv2.imwrite(str(tmp_path / "a.png"), np.zeros((8, 8, 3), np.uint8))
    seen = []
    monkeypatch.setattr(checkpoint, "load_model", lambda w: ("model", {"classes": ["car"]}))
    monkeypatch.setattr(predict, "predict_images", lambda model, files, opts: seen.append(opts.vertical) or iter(()))
    for extra, want in (([], "lines"), (["--vertical", "off"], "off")):
        p = argparse.ArgumentParser()
        predict_command.add_arguments(p)
        args = p.parse_args(["w.pt", str(tmp_path / "a.png"), "--out", str(tmp_path / "out"), "--imgsz", "64",
                             "--no-overlays", *extra])
        assert predict_command.run(args) == 0
        assert seen[-1] == want
    with pytest.raises(SystemExit):  # argparse refuses another mode, naming the choices
        p.parse_args(["w.pt", "x.png", "--out", "o", "--vertical", "both"])
