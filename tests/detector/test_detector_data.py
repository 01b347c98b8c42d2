"""Issue 10: the detector's data pipeline (letterbox, augmentation, targets) and NMS."""

from __future__ import annotations

import numpy as np
import pytest
import torch

pytest.importorskip("cv2", reason="opencv-python-headless is part of the train extra")

from omnigen.detector.data.samples import (Augment, KeypointDataset, Sample, clip_to_canvas, collate, flip_horizontal, letterbox,
                           random_affine, random_crop)
from omnigen.detector.model.boxes import box_iou_pairwise as box_iou
from omnigen.detector.prediction.nms import nms, postprocess
from omnigen.conventions import FLIP_IDX, NUM_KEYPOINTS
from omnigen.fakes import write_fake_dataset
from omnigen.taxonomy import load_taxonomy


@pytest.fixture(scope="module")
def fake(tmp_path_factory):
    root = tmp_path_factory.mktemp("fake")
    write_fake_dataset(root, 6, objects_per_frame=6, seed=2)
    return root


def _sample(rng, n=3, size=64):
    image = rng.integers(0, 255, (size, size, 3), dtype=np.uint8)
    kp = rng.uniform(-10, size + 10, (n, NUM_KEYPOINTS, 2))
    boxes = np.concatenate([kp.min(1), kp.max(1)], 1)
    mask = rng.random((n, NUM_KEYPOINTS)) < 0.8
    vis = (rng.random((n, NUM_KEYPOINTS)) < 0.5).astype(np.float32)
    from omnigen.detector.data.samples import Letterbox
    return Sample(image, np.arange(n), boxes, kp, mask, vis, 0, Letterbox(1.0, (0.0, 0.0)))


def test_flip_permutes_corners_by_flip_idx_and_mirrors_x():
    rng = np.random.default_rng(0)
    s = _sample(rng)
    f = flip_horizontal(s)
    W = s.image.shape[1]
    for j in range(NUM_KEYPOINTS):
        # corner j of the flipped object is the mirror of corner FLIP_IDX[j] of the original
        # (pixel centres at integers: column c goes to W - 1 - c)
        np.testing.assert_allclose(f.keypoints[:, j, 0], W - 1 - s.keypoints[:, FLIP_IDX[j], 0])
        np.testing.assert_allclose(f.keypoints[:, j, 1], s.keypoints[:, FLIP_IDX[j], 1])
        np.testing.assert_array_equal(f.kpt_mask[:, j], s.kpt_mask[:, FLIP_IDX[j]])
    np.testing.assert_array_equal(f.image, s.image[:, ::-1])
    assert (f.bboxes[:, 0] <= f.bboxes[:, 2]).all()
    # flipping twice is the identity
    g = flip_horizontal(f)
    np.testing.assert_allclose(g.keypoints, s.keypoints)
    np.testing.assert_array_equal(g.kpt_mask, s.kpt_mask)


def test_flip_idx_swaps_left_and_right_partners():
    """A mirrored object's left side is the original's right side: FLIP_IDX pairs each corner with
    the one that differs only in left/right."""
    from omnigen.conventions import CORNER_NAMES
    for j, k in enumerate(FLIP_IDX):
        a, b = CORNER_NAMES[j], CORNER_NAMES[k]
        assert a.replace("left", "X").replace("right", "left").replace("X", "right") == b


def test_letterbox_maps_points_both_ways():
    image = np.zeros((100, 200, 3), np.uint8)
    out, lb = letterbox(image, 64)
    assert out.shape == (64, 64, 3)
    assert lb.gain == pytest.approx(64 / 200) and lb.pad == (0.0, 16.0)
    pts = np.array([[0.0, 0.0], [200.0, 100.0], [50.0, 25.0]])
    np.testing.assert_allclose(lb.to_image(lb.to_input(pts)), pts, atol=1e-9)
    # the image's outer edges (pixel centres at integers: -0.5 and w - 0.5) land on the canvas's
    np.testing.assert_allclose(lb.to_input(np.array([[-0.5, -0.5], [199.5, 99.5]])), [[-0.5, 15.5], [63.5, 47.5]])


def test_flip_of_an_image_moves_a_bright_pixel_where_its_corner_goes():
    image = np.zeros((8, 10, 3), np.uint8)
    image[3, 2] = 255  # the pixel whose centre is (x=2, y=3)
    s = Sample(image, np.zeros(1, np.int64), np.array([[1.5, 2.5, 2.5, 3.5]]), np.full((1, 8, 2), [2.0, 3.0]),
               np.ones((1, 8), bool), np.ones((1, 8), np.float32), 0, None)
    f = flip_horizontal(s)
    ys, xs = np.nonzero(f.image[..., 0])
    np.testing.assert_allclose(f.keypoints[0, 0], [xs[0], ys[0]])
    np.testing.assert_allclose(f.bboxes[0], [xs[0] - 0.5, 2.5, xs[0] + 0.5, 3.5])


def test_affine_moves_corners_with_the_image():
    rng = np.random.default_rng(1)
    image = np.zeros((64, 64, 3), np.uint8)
    image[30:34, 20:24] = 255  # a bright square centred on (21.5, 31.5) in pixel-centre coordinates
    s = Sample(image, np.zeros(1, np.int64), np.array([[19.5, 29.5, 23.5, 33.5]]), np.full((1, 8, 2), [21.5, 31.5]),
               np.ones((1, 8), bool), np.ones((1, 8), np.float32), 0, None)
    t = random_affine(s, 0.4, 0.1, rng)
    ys, xs = np.nonzero(t.image[..., 0] > 128)
    centre = np.array([xs.mean(), ys.mean()])  # warpAffine maps pixel centres: our convention
    np.testing.assert_allclose(t.keypoints[0, 0], centre, atol=0.5)


def test_out_of_image_corners_learned_or_dropped():
    s = Sample(np.zeros((64, 64, 3), np.uint8), np.zeros(1, np.int64), np.array([[-20.0, 10, 30, 40]]),
               np.array([[[-20.0, 10]] * 4 + [[30.0, 40]] * 4]), np.ones((1, 8), bool), np.ones((1, 8), np.float32),
               0, None)
    learn = clip_to_canvas(s, "learn")
    drop = clip_to_canvas(s, "drop")
    assert learn.kpt_mask.all()  # truncated object's outside corners stay targets
    assert not drop.kpt_mask[0, :4].any() and drop.kpt_mask[0, 4:].all()
    assert not learn.kpt_visible[0, :4].any()  # outside corners are never 'visible'
    np.testing.assert_allclose(learn.bboxes[0], [-0.5, 10, 30, 40])


def test_crop_keeps_the_scale_and_moves_targets_with_the_pixels():
    rng = np.random.default_rng(3)
    s = _sample(rng, n=4, size=64)
    t = random_crop(s, 32, rng)
    assert t.image.shape == (32, 32, 3)
    # the window is a slice of the canvas: find where it came from and check the corners moved with it
    windows = np.lib.stride_tricks.sliding_window_view(s.image, (32, 32, 3))[..., 0, :, :, :]
    hits = np.argwhere((windows == t.image).all(axis=(-1, -2, -3)))
    assert len(hits) == 1
    y0, x0 = hits[0]
    np.testing.assert_allclose(t.keypoints, s.keypoints - [x0, y0])
    np.testing.assert_allclose(t.bboxes, s.bboxes - [x0, y0, x0, y0])
    assert random_crop(s, 64, rng) is s  # a window as large as the canvas is the canvas


def test_crop_stays_in_the_letterboxed_content():
    from omnigen.detector.data.samples import Letterbox
    rng = np.random.default_rng(0)
    image = np.full((64, 64, 3), 114, np.uint8)
    image[16:48] = 7  # a 64 x 32 image letterboxed into 64 x 64: content rows 16..47
    s = Sample(image, np.zeros(0, np.int64), np.zeros((0, 4)), np.zeros((0, 8, 2)), np.zeros((0, 8), bool),
               np.zeros((0, 8), np.float32), 0, Letterbox(1.0, (0.0, 16.0)))
    for _ in range(20):
        assert (random_crop(s, 32, rng).image == 7).all()  # 32 rows of content: never the padding
    for _ in range(20):  # a taller window than the content holds all of it
        assert (random_crop(s, 48, rng).image == 7).sum(axis=(1, 2)).astype(bool).sum() == 32


def test_cropped_samples_are_windows_of_the_full_input(fake):
    tax = load_taxonomy("fine")
    full = KeypointDataset(fake, tax, 128)
    crop = KeypointDataset(fake, tax, 128, augment=Augment.off(), crop=64, seed=1)
    found = 0
    for i in range(len(crop)):
        s, whole = crop[i], full.raw(i)[1]
        assert s.image.shape == (64, 64, 3)
        for k in s.keypoints:  # every kept object is one of the full input's, shifted by the window
            d = whole.keypoints - k
            match = np.flatnonzero(np.abs(d - d[:, :1]).max(axis=(1, 2)) < 1e-6)
            assert len(match) >= 1
            found += 1
    assert found > 0
    with pytest.raises(ValueError, match="crop"):
        KeypointDataset(fake, tax, 64, crop=96)


def test_dataset_targets_match_records(fake):
    tax = load_taxonomy("fine")
    data = KeypointDataset(fake, tax, 160)
    image, s = data.raw(0)
    rec = data.ds[0]
    assert s.image.shape == (160, 160, 3)
    assert len(s.cls) == len(rec.objects)
    for o, m, k in zip(rec.objects, s.kpt_mask, s.letterbox.to_image(s.keypoints)):
        np.testing.assert_array_equal(m, ~o.behind_camera)
        np.testing.assert_allclose(k[m], o.keypoints[m], atol=1e-6)
    images, targets, _ = collate([data[i] for i in range(3)])
    assert images.shape == (3, 3, 160, 160) and images.dtype == torch.float32 and images.max() <= 1
    assert targets["keypoints"].shape[1:] == (8, 2) and targets["batch_idx"].max() == 2


def test_drop_masks_corners_outside_the_image_even_inside_the_padding(fake):
    data = KeypointDataset(fake, load_taxonomy("fine"), 160, out_of_image="drop")
    for i in range(len(data)):
        rec, s = data.ds[i], data.raw(i)[1]
        for o, m in zip(rec.objects, s.kpt_mask):
            np.testing.assert_array_equal(m, ~o.behind_camera & o.in_image)


def test_augmentation_is_seeded_per_frame_and_epoch(fake):
    tax = load_taxonomy("fine")
    a = KeypointDataset(fake, tax, 96, augment=Augment(), seed=7)
    b = KeypointDataset(fake, tax, 96, augment=Augment(), seed=7)
    np.testing.assert_array_equal(a[2].image, b[2].image)
    np.testing.assert_array_equal(a[2].keypoints, b[2].keypoints)
    b.set_epoch(1)
    assert not np.array_equal(a[2].keypoints, b[2].keypoints)


def test_cached_images_give_the_same_samples_and_stay_read_only(fake, monkeypatch):
    import omnigen.detector.data.samples as data_mod

    tax = load_taxonomy("fine")
    disk = KeypointDataset(fake, tax, 96, augment=Augment(), seed=7, crop=64)
    ram = KeypointDataset(fake, tax, 96, augment=Augment(), seed=7, crop=64)
    assert ram.cache_images() == len(ram) * 96 * 96 * 3
    for i in range(len(disk)):
        a, b = disk[i], ram[i]
        np.testing.assert_array_equal(a.image, b.image)
        np.testing.assert_array_equal(a.keypoints, b.keypoints)
        np.testing.assert_array_equal(a.kpt_mask, b.kpt_mask)
    cached = ram.sample(0).image
    assert not cached.flags.writeable  # an augmentation writing into its input fails, never corrupts
    with pytest.raises(ValueError):
        cached[0, 0, 0] = 0
    monkeypatch.setattr(data_mod, "available_memory", lambda: 1000)
    with pytest.raises(MemoryError, match=r"caching 6 images at 96 px needs"):
        KeypointDataset(fake, tax, 96).cache_images()


def test_coarse_taxonomy_drops_classes(fake):
    fine = KeypointDataset(fake, load_taxonomy("fine"), 96)
    coarse = KeypointDataset(fake, load_taxonomy("coarse"), 96)
    n_fine = sum(len(fine.raw(i)[1].cls) for i in range(len(fine)))
    n_coarse = sum(len(coarse.raw(i)[1].cls) for i in range(len(coarse)))
    assert n_coarse < n_fine and max(coarse.raw(i)[1].cls.max(initial=0) for i in range(len(coarse))) <= 2


def test_nms_by_hand():
    boxes = torch.tensor([[0, 0, 10, 10], [1, 1, 11, 11], [20, 20, 30, 30], [0, 0, 10, 9.0]])
    scores = torch.tensor([0.9, 0.8, 0.7, 0.95])
    keep = nms(boxes, scores, 0.5)
    assert keep.tolist() == [3, 2]  # box 3 wins; 0 (IoU 0.9) and 1 (IoU ~0.61 with 3) go; 2 is apart
    assert box_iou(boxes[:1], boxes[1:2]).item() == pytest.approx(81 / 119)


def test_postprocess_is_class_aware():
    nc = 2
    A = 3
    pred = torch.zeros(1, 4 + nc + 24, A)
    pred[0, :4] = torch.tensor([[0.0, 0, 1], [0, 0, 1], [10, 10, 11], [10, 10, 11]])  # rows x1 y1 x2 y2
    pred[0, 4] = torch.tensor([0.9, 0.1, 0.8])  # class 0 scores
    pred[0, 5] = torch.tensor([0.1, 0.85, 0.1])  # class 1 scores
    dets = postprocess(pred, nc, conf=0.5, iou=0.5)[0]
    # anchors 0 and 1 are the same box but different classes: both kept; anchor 2 overlaps 0, same class
    assert sorted(dets.classes.tolist()) == [0, 1]
    assert dets.keypoints.shape == (2, 8, 3)


def test_postprocess_multi_label_scores_every_class_above_the_floor():
    # one anchor rated 0.6 car and 0.4 van: single-label gives the car; multi-label both, each a
    # detection of its class with its own score, as Ultralytics' validation scores a model
    nc = 3
    pred = torch.zeros(1, 4 + nc + 24, 2)
    pred[0, :4, 0] = torch.tensor([10.0, 10.0, 50.0, 40.0])
    pred[0, 4:4 + nc, 0] = torch.tensor([0.6, 0.4, 0.05])
    pred[0, :4, 1] = torch.tensor([100.0, 100.0, 140.0, 130.0])
    pred[0, 4:4 + nc, 1] = torch.tensor([0.01, 0.02, 0.3])
    single = postprocess(pred, nc, conf=0.1, iou=0.5)[0]
    assert single.classes.tolist() == [0, 2] and single.scores.tolist() == pytest.approx([0.6, 0.3])
    multi = postprocess(pred, nc, conf=0.1, iou=0.5, multi_label=True)[0]
    got = sorted(zip(multi.classes.tolist(), multi.scores.tolist()))
    assert got == [(0, pytest.approx(0.6)), (1, pytest.approx(0.4)), (2, pytest.approx(0.3))]
    assert multi.boxes[multi.classes == 1].tolist() == [[10.0, 10.0, 50.0, 40.0]]  # the anchor's own box


def test_one_label_per_box_keeps_each_boxs_best_class():
    from omnigen.detector.prediction.predict import one_label_per_box

    def det(frame, box, cls, score):
        return {"image_id": 1, "frame_id": frame, "category_id": cls, "bbox": box, "keypoints": [0.0] * 24,
                "score": score}

    a, b = [10.0, 10.0, 40.0, 30.0], [50.0, 5.0, 20.0, 20.0]
    results = [det("f1", a, 1, 0.6), det("f1", b, 3, 0.5), det("f1", a, 2, 0.4), det("f2", a, 2, 0.7),
               det("f2", a, 1, 0.8)]
    kept = one_label_per_box(results)
    assert [(r["frame_id"], r["category_id"], r["score"]) for r in kept] == [("f1", 1, 0.6), ("f1", 3, 0.5),
                                                                             ("f2", 1, 0.8)]
