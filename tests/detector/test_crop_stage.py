"""The crop stage (detector/model/crop_stage.py): cropping, crop units, orienting, the training rows and
their jitter, the model's forward and loss terms, learning corners and a front from pixels, and
prediction's use of it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from omnigen.conventions import FLIP_IDX, TURN_IDX
from omnigen.detector.model.boxes import box_area
from omnigen.detector.model.heading import image_heading, orient
from omnigen.detector.model.crop_stage import (CropNet, crop_boxes, crop_outputs, distinct_boxes, from_crop_units, jitter_boxes,
                                         mirror_corners, refine, refine_detections, rescore, split_outputs,
                                         to_crop_units, training_rois, draw_rows)
from omnigen.detector.training.loss import DetectionLoss
from omnigen.detector.model.network import DetectorConfig, KeypointDetector
from omnigen.detector.model.outputs import Detections

TINY = dict(width=0.0625, depth=0.33, max_channels=64)


def side_view(x0: float, y0: float, length: float, height: float, facing_right: bool) -> torch.Tensor:
    """Eight image corners (8, 2) of a box seen from its side, its front face on the right or left."""
    front, rear = (x0 + length, x0) if facing_right else (x0, x0 + length)
    d = 0.15 * length  # the far faces a little up and inwards
    top, bottom = y0, y0 + height
    return torch.tensor([[front, top], [front - d * (1 if facing_right else -1), top - d],
                         [rear - d * (1 if facing_right else -1), top - d], [rear, top],
                         [front, bottom], [front - d * (1 if facing_right else -1), bottom - d],
                         [rear - d * (1 if facing_right else -1), bottom - d], [rear, bottom]], dtype=torch.float32)


def test_crop_boxes_samples_the_square_about_the_box():
    img = torch.arange(64.0).view(1, 1, 8, 8)
    # pixel centres at integers (the contract's): the top-left 4x4 block spans -0.5 .. 3.5, and a box
    # on it with no margin crops those 16 pixels exactly
    c = crop_boxes(img, torch.tensor([0]), torch.tensor([[-0.5, -0.5, 3.5, 3.5]]), 4, margin=0.0)
    assert torch.equal(c[0, 0], img[0, 0, :4, :4])
    # a 2x4 box is squared about its centre (4x4 from pixel -1), and zero outside the image
    c = crop_boxes(img, torch.tensor([0]), torch.tensor([[-0.5, -0.5, 1.5, 3.5]]), 4, margin=0.0)
    assert torch.equal(c[0, 0, :, 0], torch.zeros(4)) and torch.equal(c[0, 0, :, 1:], img[0, 0, :4, :3])
    # the batch index picks the image, in the batched path as in the single-image one
    two = torch.stack([img[0], img[0] + 100])
    box = torch.tensor([[3.5, 3.5, 7.5, 7.5]])
    c = crop_boxes(two, torch.tensor([1, 0]), box.expand(2, 4), 4, margin=0.0)
    assert torch.equal(c[0], c[1] + 100) and torch.equal(c[1, 0], img[0, 0, 4:, 4:])
    assert torch.equal(crop_boxes(img, torch.tensor([0]), box, 4, margin=0.0)[0], c[1])
    assert crop_boxes(two, torch.zeros(0, dtype=torch.long), torch.zeros(0, 4), 16).shape == (0, 1, 16, 16)


def test_crop_units_put_the_crop_edges_at_one_and_mirror_as_the_image_does():
    boxes = torch.tensor([[10.0, 20.0, 50.0, 40.0]])  # 40 x 20: a 48-pixel square crop (margin 0.1)
    pts = torch.tensor([[[30.0, 30.0], [54.0, 30.0], [30.0, 6.0]]])
    t = to_crop_units(pts, boxes)
    assert torch.allclose(t, torch.tensor([[[0.0, 0.0], [1.0, 0.0], [0.0, -1.0]]]))
    assert torch.allclose(from_crop_units(t, boxes), pts)
    # mirroring a crop about its centre column: corner k of the mirror is corner FLIP_IDX[k], x negated
    k = to_crop_units(side_view(12, 24, 36, 10, True)[None], boxes)
    m = mirror_corners(k)
    assert torch.equal(m[0, 1], k[0, FLIP_IDX[1]] * torch.tensor([-1.0, 1.0])) and torch.equal(mirror_corners(m), k)


def test_jitter_moves_boxes_by_the_set_noise():
    torch.manual_seed(0)
    boxes = torch.tensor([[100.0, 50.0, 140.0, 70.0]]).expand(20000, 4)
    moved = jitter_boxes(boxes)
    wh, mwh = boxes[:, 2:] - boxes[:, :2], moved[:, 2:] - moved[:, :2]
    shift = ((moved[:, :2] + moved[:, 2:]) - (boxes[:, :2] + boxes[:, 2:])) / 2 / wh
    assert torch.allclose(shift.std(0), torch.tensor([0.06, 0.06]), atol=0.003)
    assert torch.allclose((mwh / wh).log().std(0), torch.tensor([0.1, 0.1]), atol=0.003)
    torch.manual_seed(0)
    assert torch.equal(jitter_boxes(boxes), moved)  # the trainer's seeded generator: reruns repeat


def test_orient_turns_only_the_layouts_that_disagree():
    right = side_view(10, 20, 40, 15, facing_right=True)
    k = torch.stack([right, right])
    k3 = torch.cat([k, torch.rand(2, 8, 1)], -1)
    boxes = torch.tensor([[10.0, 14.0, 50.0, 35.0]] * 2)
    h = image_heading(right[None], box_area(boxes[:1]))[0]
    out = orient(k3, box_area(boxes), torch.stack([h, -h]))
    assert torch.equal(out[0], k3[0])  # agrees: kept as ordered
    assert torch.equal(out[1], k3[1][list(TURN_IDX)])  # disagrees: front and rear swapped, visibility with them
    assert torch.equal(orient(out, box_area(boxes), torch.stack([h, h])), k3)  # the turn is its own inverse


def test_training_rois_keep_defined_headings_and_cap_the_count():
    k = side_view(0, 0, 40, 15, True)
    n = 10
    targets = {"bboxes": torch.tensor([[0.0, -6.0, 40.0, 15.0]] * n), "keypoints": k.expand(n, 8, 2).clone(),
               "kpt_mask": torch.ones(n, 8, dtype=torch.bool)}
    targets["bboxes"][1] = torch.tensor([0.0, 0.0, 3.0, 2.0])  # too small to see
    targets["kpt_mask"][2] = False  # no labelled corner: no heading
    rows = training_rois(targets)
    assert sorted(rows.tolist()) == [0, 3, 4, 5, 6, 7, 8, 9]
    torch.manual_seed(0)
    few = training_rois(targets, max_crops=3)
    assert len(few) == 3 and set(few.tolist()) <= set(rows.tolist())


def test_balanced_draw_crops_every_rare_object_and_subsamples_the_common_class():
    rows = torch.arange(100, 200)
    classes = torch.zeros(100, dtype=torch.long)
    classes[[3, 50, 97]] = 4  # three rare objects among 97 cars
    classes[[10, 20]] = 7
    torch.manual_seed(0)
    uniform = [set(draw_rows(rows, 20).tolist()) for _ in range(50)]
    torch.manual_seed(0)
    balanced = [draw_rows(rows, 20, classes) for _ in range(50)]
    rare = {103, 150, 197, 110, 120}
    # weight 1/3 and 1/2 against 1/95: the rare rows are drawn nearly always, uniformly about a fifth of the time
    assert np.mean([len(rare & set(b.tolist())) for b in balanced]) > 4.5
    assert np.mean([len(rare & u) for u in uniform]) < 2
    for b in balanced:  # without replacement, from the candidates
        assert len(b) == 20 and len(set(b.tolist())) == 20 and set(b.tolist()) <= set(rows.tolist())
    torch.manual_seed(0)
    assert torch.equal(draw_rows(rows, 20, classes), balanced[0])  # the trainer's seed fixes the draw
    assert torch.equal(draw_rows(rows[:5], 20, classes[:5]), rows[:5])  # fewer than the cap: all of them


def test_a_class_naming_stage_draws_its_training_crops_balanced(monkeypatch):
    from omnigen.detector.training import step as train_step

    class Drawn(Exception):
        """Stops the step once the rows are asked for: nothing after them is under test."""

    def stub(targets, balanced=False):
        raise Drawn(balanced)

    monkeypatch.setattr(train_step, "training_rois", stub)
    seen = []
    for classes in (False, True):
        model = KeypointDetector(DetectorConfig(num_classes=3, kpt_heading=True, heading_crop=32, crop_classes=classes,
                                                **TINY))
        step = train_step.TrainStep(model, model, None, None, None, None, None)
        with pytest.raises(Drawn) as drawn:
            step(torch.rand(1, 3, 64, 64), {})
        seen.append(drawn.value.args[0])
    assert seen == [False, True]


def test_config_checks_the_crop_side():
    for bad in (10, -16, 1.5):
        with pytest.raises(ValueError, match="heading_crop"):
            DetectorConfig(num_classes=3, heading_crop=bad, **TINY)
    assert DetectorConfig.from_dict(DetectorConfig(num_classes=3, heading_crop=32, **TINY).to_dict()).heading_crop == 32


def test_forward_crops_and_the_loss_trains_the_crop_net():
    torch.manual_seed(0)
    model = KeypointDetector(DetectorConfig(num_classes=3, kpt_heading=True, heading_crop=32, **TINY))
    k = torch.stack([side_view(4, 20, 30, 12, True), side_view(20, 30, 30, 12, False)])
    targets = {"batch_idx": torch.tensor([0.0, 1.0]), "cls": torch.tensor([0.0, 2.0]),
               "bboxes": torch.tensor([[4.0, 15.5, 34.0, 32.0], [15.5, 25.5, 50.0, 42.0]]), "keypoints": k,
               "kpt_mask": torch.ones(2, 8, dtype=torch.bool), "kpt_visible": torch.ones(2, 8)}
    rows = training_rois(targets)
    out = model(torch.rand(2, 3, 64, 64), (rows, targets["batch_idx"][rows], targets["bboxes"][rows]))
    assert out.crop_heading.shape == (2, 3) and out.crop_corners.shape == (2, 8, 2) and torch.equal(out.crop_rows, rows)
    total, parts = DetectionLoss(3)(out, targets)
    assert 0 < float(parts["heading_crop"]) < 2 and float(parts["crop_corners"]) > 0
    # the corner term is the L1 in crop units of the boxes the crops were cut about
    want = (out.crop_corners.float() - to_crop_units(k[rows], targets["bboxes"][rows])).abs().sum(-1).mean()
    assert torch.isclose(parts["crop_corners"], want.detach(), rtol=1e-5)
    total.backward()
    assert model.crop_net.out.weight.grad.abs().sum() > 0
    # without the stage there is no term, and crops are refused with the reason
    plain = KeypointDetector(DetectorConfig(num_classes=3, kpt_heading=True, **TINY))
    assert plain.crop_net is None
    plain_parts = DetectionLoss(3)(plain(torch.rand(2, 3, 64, 64)), targets)[1]
    assert float(plain_parts["heading_crop"]) == 0 and float(plain_parts["crop_corners"]) == 0
    with pytest.raises(ValueError, match="heading_crop is 0"):
        plain(torch.rand(2, 3, 64, 64), (rows, targets["batch_idx"][rows], targets["bboxes"][rows]))


def arrow_images(rng: np.random.Generator, n: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """n 64x64 images of one grey box each with a bright nose on its front end, facing left or right
    at random, the two layouts each other's mirror images: (images, boxes, corners, facing_right)."""
    images = torch.zeros(n, 3, 64, 64)
    boxes, corners, right = [], [], []
    for i in range(n):
        x0, y0 = int(rng.integers(2, 20)), int(rng.integers(10, 40))
        r = bool(rng.random() < 0.5)
        images[i, :, y0:y0 + 12, x0:x0 + 40] = 0.4
        nose = slice(x0 + 32, x0 + 40) if r else slice(x0, x0 + 8)
        images[i, :, y0 + 3:y0 + 9, nose] = 1.0
        boxes.append([x0, y0, x0 + 40, y0 + 12])
        k = side_view(x0, y0 + 2, 40, 10, True)
        if not r:  # the mirror image, corners renumbered as the contract's flip does (its near side is the other one)
            k = k[list(FLIP_IDX)] * torch.tensor([-1.0, 1.0]) + torch.tensor([2 * x0 + 40.0, 0.0])
        corners.append(k)
        right.append(r)
    return images, torch.tensor(boxes, dtype=torch.float32), torch.stack(corners), torch.tensor(right)


def test_the_crop_net_learns_corners_and_a_front_it_can_see():
    """A front the box alone cannot give away (the same box faces either way; only the bright nose
    says which) and the corners are learned from crops about moved boxes, and refining detections
    given turned, misplaced layouts puts them right."""
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    net = CropNet(32, width=8)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    for _ in range(150):
        images, boxes, corners, _ = arrow_images(rng, 32)
        moved = jitter_boxes(boxes)
        h, t, _ = crop_outputs(net, images, torch.arange(32), moved, 32)
        loss = ((1 - torch.cosine_similarity(h, image_heading(corners, box_area(boxes)), dim=-1)).mean()
                + (t - to_crop_units(corners, moved)).abs().sum(-1).mean())
        opt.zero_grad()
        loss.backward()
        opt.step()
    net.eval()
    images, boxes, corners, right = arrow_images(np.random.default_rng(1), 64)
    kp = torch.cat([corners[:, list(TURN_IDX)] + 9.0, torch.ones(64, 8, 1)], -1)  # turned and moved
    with torch.no_grad():
        dets = [Detections(boxes[i:i + 1], torch.ones(1), torch.zeros(1, dtype=torch.long), kp[i:i + 1]) for i in range(64)]
        fixed = torch.cat([d.keypoints for d in refine_detections(net, 32, images, dets)])
    err = (fixed[..., :2] - corners).norm(dim=-1).mean(-1)  # mean corner error per object, px (boxes 40 x 12)
    assert float(err.median()) < 3.0, err.median()
    front_right = fixed[:, [0, 1, 4, 5], 0].mean(-1) > fixed[:, [2, 3, 6, 7], 0].mean(-1)
    assert float((front_right == right).float().mean()) > 0.9
    assert torch.equal(fixed[..., 2], kp[..., 2])  # the visibility channel is the head's


def test_refine_detections_stops_at_max_refine():
    """Past max_refine an image's detections keep the head's corners; before it each takes its crop's
    corners, turned where the crop's heading disagrees with them."""
    torch.manual_seed(0)
    net = CropNet(16, width=8).eval()
    # seen from the front: the front face (0, 1, 5, 4) the big square, the rear one small behind it
    facing = torch.tensor([[10, 10], [50, 10], [40, 20], [20, 20], [10, 50], [50, 50], [40, 40], [20, 40]],
                          dtype=torch.float32)
    shift = torch.arange(5.0)[:, None]  # five objects, one size: the crop places each one's corners alike
    boxes = torch.tensor([[10.0, 10.0, 50.0, 50.0]]) + shift
    kp = torch.cat([torch.rand(5, 8, 2) * 60, torch.rand(5, 8, 1)], -1)
    assert image_heading(facing[None], box_area(boxes[:1]))[0, 2] > 0
    # a constant output, its own mirror image: "the rear faces the camera", and the facing layout
    const = torch.cat([torch.tensor([0.0, 0.0, -1.0]), to_crop_units(facing[None], boxes[:1]).reshape(-1)])
    with torch.no_grad():
        net.out.weight.zero_()
        net.out.bias.copy_(const)
        dets = [Detections(boxes, torch.linspace(1, 0.5, 5), torch.zeros(5, dtype=torch.long), kp)]
        out = refine_detections(net, 16, torch.rand(1, 3, 64, 64), dets, max_refine=3)[0]
    want = torch.cat([facing + shift[:3, :, None], kp[:3, :, 2:]], -1)[:, list(TURN_IDX)]
    assert torch.allclose(out.keypoints[:3], want, atol=1e-4) and torch.equal(out.keypoints[3:], kp[3:])
    assert torch.equal(out.boxes, boxes) and torch.equal(out.scores, dets[0].scores)


def test_class_copies_of_a_box_are_cropped_once_and_take_one_place():
    # multi-label prediction: box A rated car (0.9) and van (0.5), B and C once each; with room for
    # two boxes, A's two detections and B take the crop's corners, C keeps the head's
    torch.manual_seed(0)
    net = CropNet(16, width=8).eval()
    a, b, c = [10.0, 10.0, 50.0, 30.0], [60.0, 5.0, 90.0, 40.0], [5.0, 40.0, 30.0, 60.0]
    boxes = torch.tensor([a, b, a, c])
    kp = torch.cat([torch.rand(4, 8, 2) * 60, torch.rand(4, 8, 1)], -1)
    kp[2] = kp[0]  # copies share the anchor's corners
    dets = [Detections(boxes, torch.tensor([0.9, 0.7, 0.5, 0.4]), torch.tensor([0, 0, 1, 0]), kp)]
    images = torch.rand(1, 3, 64, 96)
    with torch.no_grad():
        out = refine_detections(net, 16, images, dets, max_refine=2)[0]
        alone, _ = refine(net, 16, images, torch.zeros(2, dtype=torch.long), boxes[:2], kp[:2])
    assert torch.allclose(out.keypoints[[0, 1]], alone, atol=1e-5)
    assert torch.equal(out.keypoints[2], out.keypoints[0])  # the van copy: A's crop, once
    assert torch.equal(out.keypoints[3], kp[3])  # C is past the two boxes refined
    first, rank = distinct_boxes(boxes)
    assert first.tolist() == [0, 1, 3] and rank.tolist() == [0, 1, 0, 2]


def _labelled_batch() -> dict[str, torch.Tensor]:
    k = torch.stack([side_view(4, 20, 30, 12, True), side_view(20, 30, 30, 12, False)])
    return {"batch_idx": torch.tensor([0.0, 1.0]), "cls": torch.tensor([0.0, 2.0]),
            "bboxes": torch.tensor([[4.0, 15.5, 34.0, 32.0], [15.5, 25.5, 50.0, 42.0]]), "keypoints": k,
            "kpt_mask": torch.ones(2, 8, dtype=torch.bool), "kpt_visible": torch.ones(2, 8)}


def test_train_step_crops_the_labelled_boxes_and_trains_the_crop_net():
    from omnigen.detector.training.ema import ModelEMA
    from omnigen.detector.training.step import TrainStep

    torch.manual_seed(0)
    model = KeypointDetector(DetectorConfig(num_classes=3, kpt_heading=True, heading_crop=16, **TINY))
    before = {k: v.clone() for k, v in model.crop_net.state_dict().items()}
    opt = torch.optim.AdamW(model.parameters(), lr=1e-2)
    step = TrainStep(model, model, DetectionLoss(3), opt, torch.amp.GradScaler(enabled=False),
                     ModelEMA(model, 0.9999, 2000.0), None)
    parts = step(torch.rand(2, 3, 64, 64), _labelled_batch())
    assert 0 < float(parts["heading_crop"]) < 2 and float(parts["crop_corners"]) > 0
    assert not torch.equal(model.crop_net.out.weight, before["out.weight"])
    # a batch without labelled objects: no crops, no term, and the step still runs
    empty = {k: v[:0] for k, v in _labelled_batch().items()}
    empty_parts = step(torch.rand(2, 3, 64, 64), empty)
    assert float(empty_parts["heading_crop"]) == 0 and float(empty_parts["crop_corners"]) == 0


def test_prediction_refines_before_mapping_back_to_the_image():
    """infer_batch places each detection's corners from its crop and hands back image coordinates:
    a constant crop net (a front view's layout, its own mirror image, and "the rear faces the
    camera", so every layout is turned) against the same model without the stage."""
    from omnigen.detector.data.samples import letterbox
    from omnigen.detector.prediction.predict import PredictOptions, infer_batch

    torch.manual_seed(0)
    model = KeypointDetector(DetectorConfig(num_classes=3, kpt_heading=True, heading_crop=16, **TINY)).eval()
    facing = torch.tensor([[10, 10], [50, 10], [40, 20], [20, 20], [10, 50], [50, 50], [40, 40], [20, 40]],
                          dtype=torch.float32)
    layout = to_crop_units(facing[None], torch.tensor([[10.0, 10.0, 50.0, 50.0]]))
    with torch.no_grad():
        model.crop_net.out.weight.zero_()
        model.crop_net.out.bias.copy_(torch.cat([torch.tensor([0.0, 0.0, -1.0]), layout.reshape(-1)]))
    image = (np.random.default_rng(0).random((48, 80, 3)) * 255).astype(np.uint8)  # letterboxed: padded rows
    boxed, lb = letterbox(image, 64)
    opts = PredictOptions(imgsz=64, conf=0.0, max_det=50, vertical="off")  # the crop stage's corners alone
    refined = infer_batch(model, [boxed], [lb], opts)[0]
    net, model.crop_net = model.crop_net, None
    plain = infer_batch(model, [boxed], [lb], opts)[0]
    model.crop_net = net
    assert np.array_equal(refined["boxes"], plain["boxes"]) and len(plain["boxes"]) > 10
    b = torch.from_numpy(plain["boxes"]).float()
    xy = from_crop_units(layout.expand(len(b), 8, 2), b)[:, list(TURN_IDX)].numpy()
    np.testing.assert_allclose(refined["keypoints"][..., :2], xy, rtol=0, atol=1e-3)
    np.testing.assert_allclose(refined["keypoints"][..., 2], plain["keypoints"][:, list(TURN_IDX), 2], rtol=0, atol=1e-6)


def test_weights_without_a_crop_stage_fine_tune_with_one(tmp_path):
    """--weights from a plain model into a crop-stage one: every detector tensor is the
    checkpoint's, the crop stage starts fresh, and a note says so."""
    from omnigen.detector.model.checkpoint import load_pretrained, save_checkpoint
    from omnigen.taxonomy import load_taxonomy

    torch.manual_seed(0)
    cfg = DetectorConfig(num_classes=12, kpt_heading=True, **TINY)
    src = KeypointDetector(cfg)
    path = tmp_path / "plain.pt"
    save_checkpoint(path, {"config": cfg.to_dict(), "model": src.state_dict(),
                           "classes": list(load_taxonomy("fine").classes)})
    model = KeypointDetector(DetectorConfig(num_classes=12, kpt_heading=True, heading_crop=64, **TINY))
    notes = load_pretrained(model, path, load_taxonomy("fine"))
    assert len(notes) == 1 and "crop stage" in notes[0] and "starts fresh" in notes[0]
    for k, v in src.state_dict().items():
        assert torch.equal(model.state_dict()[k], v), k
    other = KeypointDetector(DetectorConfig(num_classes=12, kpt_heading=False, heading_crop=64, **TINY))
    with pytest.raises(ValueError, match="kpt_heading"):  # any other field still must match
        load_pretrained(other, path, load_taxonomy("fine"))


def test_predicting_without_the_crop_stage_keeps_the_detections_and_the_heads_corners(tmp_path):
    """crop_net = None: the same boxes and scores, the head's corners; with the stage (a constant
    crop net) the corners are the crop's."""
    from omnigen.detector.model.checkpoint import save_checkpoint
    from omnigen.detector.prediction.predict import load_for_prediction, predict_split
    from omnigen.fakes import write_fake_dataset
    from omnigen.taxonomy import load_taxonomy

    torch.manual_seed(0)
    classes = list(load_taxonomy("fine").classes)
    cfg = DetectorConfig(num_classes=len(classes), kpt_heading=True, heading_crop=16, **TINY)
    model = KeypointDetector(cfg)
    with torch.no_grad():  # every crop says: the front view's layout, front towards the camera
        model.crop_net.out.weight.zero_()
        model.crop_net.out.bias.copy_(torch.cat([torch.tensor([0.0, 0.0, 1.0]), torch.linspace(-0.9, 0.9, 16)]))
    path = tmp_path / "crop.pt"
    save_checkpoint(path, {"config": cfg.to_dict(), "model": model.state_dict(), "classes": classes})
    root = tmp_path / "ds"
    write_fake_dataset(root, n_frames=2, objects_per_frame=3)
    loaded, state = load_for_prediction(path, "cpu")
    staged = predict_split(loaded, state, root, split=None, imgsz=64)
    loaded.crop_net = None
    plain = predict_split(loaded, state, root, split=None, imgsz=64)
    assert len(staged) == len(plain) > 0
    assert [(d["image_id"], d["bbox"], d["score"]) for d in staged] == [(d["image_id"], d["bbox"], d["score"]) for d in plain]
    kp_s = np.array([d["keypoints"] for d in staged]).reshape(len(staged), 8, 3)
    kp_p = np.array([d["keypoints"] for d in plain]).reshape(len(plain), 8, 3)
    assert not np.allclose(kp_s[..., :2], kp_p[..., :2], atol=1.0)  # the crop's corners, not the head's
    np.testing.assert_array_equal(kp_s[..., 2], kp_p[..., 2])  # visibility stays the head's either way


# ---- a crop stage that names classes (DetectorConfig.crop_classes) ----

def test_crop_classes_need_the_stage_and_widen_only_its_last_layer():
    with pytest.raises(ValueError, match="crop_classes"):
        DetectorConfig(num_classes=3, crop_classes=True, **TINY)
    model = KeypointDetector(DetectorConfig(num_classes=3, kpt_heading=True, heading_crop=16, crop_classes=True, **TINY))
    assert model.crop_net.num_classes == 3 and model.crop_net.out.out_features == 3 + 16 + 3
    h, t, c = split_outputs(torch.arange(22.0)[None])
    assert h.tolist() == [[0.0, 1.0, 2.0]] and t.shape == (1, 8, 2) and c.tolist() == [[19.0, 20.0, 21.0]]
    assert split_outputs(torch.zeros(1, 19))[2] is None  # a stage without classes


def test_the_crop_class_loss_is_the_cross_entropy_of_the_labelled_classes():
    torch.manual_seed(0)
    model = KeypointDetector(DetectorConfig(num_classes=3, kpt_heading=True, heading_crop=32, crop_classes=True, **TINY))
    targets = _labelled_batch()
    rows = training_rois(targets)
    out = model(torch.rand(2, 3, 64, 64), (rows, targets["batch_idx"][rows], targets["bboxes"][rows]))
    assert out.crop_logits.shape == (2, 3)
    total, parts = DetectionLoss(3)(out, targets)
    want = torch.nn.functional.cross_entropy(out.crop_logits.float(), targets["cls"].long()[rows])
    assert torch.isclose(parts["crop_cls"], want.detach(), rtol=1e-5) and float(want.detach()) > 0
    total.backward()
    assert model.crop_net.out.weight.grad[-3:].abs().sum() > 0  # the class rows learn
    plain = KeypointDetector(DetectorConfig(num_classes=3, kpt_heading=True, heading_crop=32, **TINY))
    out = plain(torch.rand(2, 3, 64, 64), (rows, targets["batch_idx"][rows], targets["bboxes"][rows]))
    assert out.crop_logits is None and float(DetectionLoss(3)(out, targets)[1]["crop_cls"]) == 0


def test_the_crop_net_learns_classes_it_can_see():
    """Bright boxes are class 1, dark ones class 0, the same shapes: the crop stage learns to tell."""
    torch.manual_seed(0)
    rng = np.random.default_rng(0)
    net = CropNet(32, width=8, num_classes=2)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)

    def batch(n):
        images, boxes, _, _ = arrow_images(rng, n)
        labels = torch.from_numpy(rng.integers(0, 2, n))
        return images * torch.where(labels == 1, 1.0, 0.5)[:, None, None, None], boxes, labels

    for _ in range(60):
        images, boxes, labels = batch(32)
        loss = torch.nn.functional.cross_entropy(crop_outputs(net, images, torch.arange(32), jitter_boxes(boxes), 32)[2],
                                                 labels)
        opt.zero_grad()
        loss.backward()
        opt.step()
    images, boxes, labels = batch(64)
    with torch.no_grad():
        _, probs = refine(net.eval(), 32, images, torch.arange(64), boxes, torch.zeros(64, 8, 3))
    assert probs.shape == (64, 2) and torch.allclose(probs.sum(-1), torch.ones(64))
    assert float((probs.argmax(-1) == labels).float().mean()) > 0.9


def test_refined_detections_are_rescored_by_their_crops_class_and_sorted_again():
    # box A rated car 0.9 and van 0.5, B car 0.7, C car 0.4; room for two boxes. The crop says A
    # is a van (0.8 van, 0.2 car) and B a van too (same constant net): sqrt(score * p)
    net = CropNet(16, width=8, num_classes=2).eval()
    with torch.no_grad():
        net.out.weight.zero_()
        net.out.bias.zero_()
        net.out.bias[-2:] = torch.tensor([0.0, float(np.log(4.0))])  # softmax: 0.2 car, 0.8 van
    a, b, c = [10.0, 10.0, 50.0, 30.0], [60.0, 5.0, 90.0, 40.0], [5.0, 40.0, 30.0, 60.0]
    boxes = torch.tensor([a, b, a, c])
    dets = [Detections(boxes, torch.tensor([0.9, 0.7, 0.5, 0.4]), torch.tensor([0, 0, 1, 0]), torch.rand(4, 8, 3))]
    images = torch.rand(1, 3, 64, 96)
    with torch.no_grad():
        out = refine_detections(net, 16, images, dets, max_refine=2)[0]
        kept = refine_detections(net, 16, images, dets, max_refine=2, rescore_classes=False)[0]
    want = {(0, 1): (0.5 * 0.8) ** 0.5, (0, 0): (0.9 * 0.2) ** 0.5, (1, 0): (0.7 * 0.2) ** 0.5, (2, 0): 0.4}
    got = {}
    for box, cls, score in zip(out.boxes.tolist(), out.classes.tolist(), out.scores.tolist()):
        got[([a, b, c].index(box), cls)] = score
    assert got.keys() == want.keys() and all(abs(got[k] - want[k]) < 1e-5 for k in want)
    assert out.scores.tolist() == sorted(out.scores.tolist(), reverse=True)  # best first again
    assert (out.classes[0], out.boxes[0].tolist()) == (1, a)  # A's van copy now leads
    by_key = {(tuple(bx), int(cl)): kp for bx, cl, kp in zip(out.boxes.tolist(), out.classes, out.keypoints)}
    for bx, cl, kp in zip(kept.boxes.tolist(), kept.classes, kept.keypoints):  # rows move with their boxes
        assert torch.equal(by_key[(tuple(bx), int(cl))], kp)
    assert torch.equal(kept.scores, dets[0].scores)  # rescore_classes=False: the head's scores
    assert rescore(torch.tensor([0.25]), torch.tensor([1]), torch.tensor([[0.0, 1.0]])).item() == 0.5


def test_a_single_label_detection_takes_the_class_whose_rescored_score_is_best():
    # the crop says 0.2 car, 0.8 van; each class's head score at the anchor is rescored by it
    net = CropNet(16, width=8, num_classes=2).eval()
    with torch.no_grad():
        net.out.weight.zero_()
        net.out.bias.zero_()
        net.out.bias[-2:] = torch.tensor([0.0, float(np.log(4.0))])
    a = [10.0, 10.0, 50.0, 30.0]
    images = torch.rand(1, 3, 64, 96)

    def single(car: float, van: float) -> Detections:
        dets = [Detections(torch.tensor([a]), torch.tensor([car]), torch.tensor([0]), torch.rand(1, 8, 3),
                           class_scores=torch.tensor([[car, van]]))]
        with torch.no_grad():
            return refine_detections(net, 16, images, dets)[0]
    kept = single(0.6, 0.05)  # car sqrt(0.6 * 0.2) = 0.35 beats van sqrt(0.05 * 0.8) = 0.2
    assert kept.classes.tolist() == [0] and abs(kept.scores.item() - (0.6 * 0.2) ** 0.5) < 1e-5
    named = single(0.6, 0.3)  # van sqrt(0.3 * 0.8) = 0.49 beats car 0.35: the crop names the class
    assert named.classes.tolist() == [1] and abs(named.scores.item() - (0.3 * 0.8) ** 0.5) < 1e-5


def test_prediction_can_keep_the_heads_scores_of_a_class_naming_stage():
    from omnigen.detector.data.samples import letterbox
    from omnigen.detector.prediction.predict import PredictOptions, infer_batch

    torch.manual_seed(0)
    model = KeypointDetector(DetectorConfig(num_classes=3, kpt_heading=True, heading_crop=16, crop_classes=True,
                                            **TINY)).eval()
    image = (np.random.default_rng(0).random((64, 64, 3)) * 255).astype(np.uint8)
    boxed, lb = letterbox(image, 64)
    opts = PredictOptions(imgsz=64, conf=0.0, max_det=50, multi_label=True)  # as evaluation predicts
    rescored = infer_batch(model, [boxed], [lb], opts)[0]
    head = infer_batch(model, [boxed], [lb], replace(opts, crop_classes=False))[0]
    net, model.crop_net = model.crop_net, None
    plain = infer_batch(model, [boxed], [lb], opts)[0]
    model.crop_net = net
    assert np.array_equal(head["scores"], plain["scores"]) and len(plain["scores"]) > 10
    assert not np.allclose(np.sort(rescored["scores"]), np.sort(plain["scores"]))


def test_fine_tuning_a_class_naming_stage_across_taxonomies_starts_its_class_rows_fresh(tmp_path):
    from omnigen.detector.model.checkpoint import load_pretrained, save_checkpoint
    from omnigen.taxonomy import load_taxonomy

    torch.manual_seed(0)
    fine = load_taxonomy("fine")
    cfg = DetectorConfig(num_classes=len(fine.classes), kpt_heading=True, heading_crop=16, **TINY)
    path = tmp_path / "crop.pt"
    src = KeypointDetector(cfg)
    save_checkpoint(path, {"config": cfg.to_dict(), "model": src.state_dict(), "classes": list(fine.classes)})
    # the same classes, now named by the stage: only its last layer (wider) starts fresh
    model = KeypointDetector(DetectorConfig(num_classes=len(fine.classes), kpt_heading=True, heading_crop=16,
                                            crop_classes=True, **TINY))
    notes = load_pretrained(model, path, fine)
    assert len(notes) == 1 and "crop_net.out.weight" in notes[0] and "crop_net.out.bias" in notes[0]
    assert torch.equal(model.crop_net.hidden[0].weight, src.crop_net.hidden[0].weight)


def two_anchor_prediction(boxes: list[list[float]], head: list[list[float]], crop: list[float], opts):
    """infer_batch of a two-class crop-stage model whose head gives two anchors `boxes` with class
    scores `head`, and whose crop stage says `crop` (class probabilities) of every crop."""
    from omnigen.detector.data.samples import letterbox
    from omnigen.detector.prediction.predict import infer_batch

    model = KeypointDetector(DetectorConfig(num_classes=2, kpt_heading=True, heading_crop=16, crop_classes=True,
                                            **TINY)).eval()
    with torch.no_grad():
        model.crop_net.out.weight.zero_()
        model.crop_net.out.bias.zero_()
        model.crop_net.out.bias[-2:] = torch.tensor(crop).log()
    pred = torch.zeros(1, 4 + 2 + 24, 2)
    pred[0, :4] = torch.tensor(boxes).T
    pred[0, 4:6] = torch.tensor(head).T
    model.infer = lambda x: pred
    boxed, lb = letterbox(np.zeros((64, 64, 3), dtype=np.uint8), 64)
    return infer_batch(model, [boxed], [lb], opts)[0]


def test_single_label_prediction_takes_the_class_the_head_and_the_crop_agree_on():
    """omnigen predict (one label a box) with a stage that names classes: box A, rated car 0.5 and
    van 0.3 by the head, is a van once its crop says van (0.9): sqrt(0.3 * 0.9) = 0.52 against
    sqrt(0.5 * 0.1) = 0.22; box B, car 0.6 alone, falls under the 0.25 floor (sqrt(0.6 * 0.1))."""
    from omnigen.detector.prediction.predict import PredictOptions

    boxes, head = [[10.0, 10.0, 40.0, 30.0], [50.0, 10.0, 60.0, 40.0]], [[0.5, 0.3], [0.6, 0.01]]
    opts = PredictOptions(imgsz=64, conf=0.25, max_det=10)
    got = two_anchor_prediction(boxes, head, [0.1, 0.9], opts)
    assert got["classes"].tolist() == [1] and abs(float(got["scores"][0]) - (0.3 * 0.9) ** 0.5) < 1e-5
    kept = two_anchor_prediction(boxes, head, [0.1, 0.9], replace(opts, crop_classes=False))
    assert kept["classes"].tolist() == [0, 0] and np.allclose(sorted(kept["scores"]), [0.5, 0.6])


def test_single_label_prediction_relabels_after_nms_so_one_object_stays_one_detection():
    """Two anchors on one object (IoU > 0.7): the head rates A car 0.8 / van 0.3 and B car 0.7 /
    van 0.35, the crop says car 0.7. One detection comes out, A as car (sqrt(0.8 * 0.7)), not
    a car and a van that per-class NMS of class copies would each keep."""
    from omnigen.detector.prediction.predict import PredictOptions

    got = two_anchor_prediction([[10.0, 10.0, 40.0, 30.0], [11.0, 10.0, 41.0, 30.0]], [[0.8, 0.3], [0.7, 0.35]],
                                [0.7, 0.3], PredictOptions(imgsz=64, conf=0.25, max_det=10))
    assert got["classes"].tolist() == [0] and abs(float(got["scores"][0]) - (0.8 * 0.7) ** 0.5) < 1e-5


def test_postprocess_can_carry_every_class_score_and_take_keeps_fields_together():
    from omnigen.detector.prediction.nms import postprocess

    pred = torch.zeros(1, 4 + 3 + 24, 2)
    pred[0, :4, 0] = torch.tensor([0.0, 0.0, 10.0, 10.0])
    pred[0, :4, 1] = torch.tensor([20.0, 0.0, 30.0, 10.0])
    pred[0, 4:7, 0] = torch.tensor([0.2, 0.9, 0.1])
    pred[0, 4:7, 1] = torch.tensor([0.5, 0.05, 0.3])
    det = postprocess(pred, 3, conf=0.25, class_scores=True)[0]
    assert det.classes.tolist() == [1, 0]
    assert torch.allclose(det.class_scores, torch.tensor([[0.2, 0.9, 0.1], [0.5, 0.05, 0.3]]))
    assert postprocess(pred, 3, conf=0.25)[0].class_scores is None
    one = det.take(torch.tensor([1]))
    assert one.classes.tolist() == [0] and torch.allclose(one.class_scores, torch.tensor([[0.5, 0.05, 0.3]]))
    assert len(det.take(det.scores > 0.6)) == 1


def test_a_split_stage_gives_the_corners_from_one_net_and_the_classes_from_another():
    from omnigen.detector.model.crop_stage import SplitCropNet

    torch.manual_seed(0)
    net = SplitCropNet(32, 5).eval()
    x = torch.rand(3, 3, 32, 32)
    h, t, logits = split_outputs(net(x))
    h1, t1, none = split_outputs(net.corners(x))
    _, _, l2 = split_outputs(net.classes(x))
    assert none is None and net.corners.num_classes == 0 and net.num_classes == 5
    assert torch.equal(h, h1) and torch.equal(t, t1) and torch.equal(logits, l2)
    # each net's loss reaches only its own parameters: the classes cannot cost the corners
    net.train()
    _, _, logits = split_outputs(net(x))
    torch.nn.functional.cross_entropy(logits, torch.tensor([0, 1, 4])).backward()
    assert all(p.grad is None or not p.grad.any() for p in net.corners.parameters())
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in net.classes.parameters())
    with pytest.raises(ValueError, match="num_classes"):
        SplitCropNet(32, 0)


def test_the_detector_builds_a_split_stage_only_with_classes_and_predicts_with_it():
    from omnigen.detector.model.crop_stage import SplitCropNet

    with pytest.raises(ValueError, match="crop_split"):
        DetectorConfig(num_classes=3, heading_crop=32, crop_split=True, **TINY)
    cfg = DetectorConfig(num_classes=3, kpt_heading=True, heading_crop=32, crop_classes=True, crop_split=True, **TINY)
    assert DetectorConfig.from_dict(cfg.to_dict()).crop_split is True
    model = KeypointDetector(cfg).eval()
    assert isinstance(model.crop_net, SplitCropNet)
    assert {k.split(".")[1] for k in model.state_dict() if k.startswith("crop_net.")} == {"corners", "classes"}
    boxes = torch.tensor([[4.0, 4.0, 40.0, 30.0]])
    kpts, probs = refine(model.crop_net, 32, torch.rand(1, 3, 64, 64), torch.zeros(1, dtype=torch.long), boxes,
                         torch.zeros(1, 8, 3))
    assert kpts.shape == (1, 8, 3) and probs.shape == (1, 3) and torch.allclose(probs.sum(-1), torch.ones(1))


def test_crop_position_says_where_the_crop_was_cut_and_mirrors_with_the_image():
    from omnigen.detector.model.crop_stage import crop_position, mirror_position

    hw = torch.tensor([480, 640])
    boxes = torch.tensor([[309.5, 229.5, 329.5, 249.5], [0.0, 0.0, 64.0, 32.0]])
    where = crop_position(boxes, hw)
    assert torch.allclose(where[0, :2], torch.zeros(2), atol=1e-6)  # centred on the image's centre
    assert torch.allclose(where[1, :2], torch.tensor([(32.0 - 319.5) / 640, (16.0 - 239.5) / 640]))
    assert torch.allclose(where[:, 2], torch.log(torch.tensor([20.0, 64.0]) * 1.2 / 640))
    mirrored = torch.stack([639.0 - boxes[:, 2], boxes[:, 1], 639.0 - boxes[:, 0], boxes[:, 3]], 1)
    assert torch.allclose(crop_position(mirrored, hw), mirror_position(where), atol=1e-6)


def test_a_stage_told_where_its_crops_were_learns_what_the_crop_alone_cannot_say():
    """Identical crops whose corners lie one way left of the image's centre and the other way right
    of it (as vertical edges point at a vanishing point): a net told the position learns them, one
    without it cannot. It needs the position, and a split stage gives it to the corners' net only."""
    from omnigen.detector.model.crop_stage import SplitCropNet, crop_position

    def batch(n, gen):
        boxes = torch.rand(n, 1, generator=gen) * 560 + torch.tensor([[0.0, 200.0, 40.0, 240.0]])
        where = crop_position(boxes, torch.tensor([480, 640]))
        target = torch.zeros(n, 8, 2)
        target[:, 4:, 0] = where[:, :1] * 2  # the bottom face leans towards the image's sides
        return torch.full((n, 3, 32, 32), 0.5), where, target

    errors = {}
    for position in (False, True):
        torch.manual_seed(0)
        gen = torch.Generator().manual_seed(0)
        net = CropNet(32, width=8, position=position)
        opt = torch.optim.Adam(net.parameters(), lr=3e-3)
        for _ in range(150):
            x, where, target = batch(32, gen)
            _, t, _ = split_outputs(net(x, where))
            loss = (t - target).abs().mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        net.eval()
        x, where, target = batch(64, gen)
        with torch.no_grad():
            errors[position] = float((split_outputs(net(x, where))[1] - target).abs().mean())
    assert errors[True] < 0.3 * errors[False], errors
    with pytest.raises(ValueError, match="crop_position is needed"):
        CropNet(32, width=8, position=True)(torch.rand(2, 3, 32, 32))
    split = SplitCropNet(32, 3, width=8, position=True)
    assert split.corners.position and not split.classes.position
    assert split(torch.rand(2, 3, 32, 32), torch.zeros(2, 3)).shape == (2, 3 + 16 + 3)
    with pytest.raises(ValueError, match="crop_position"):
        DetectorConfig(num_classes=3, crop_position=True, **TINY)
    cfg = DetectorConfig(num_classes=3, kpt_heading=True, heading_crop=32, crop_position=True, **TINY)
    assert DetectorConfig.from_dict(cfg.to_dict()).crop_position is True
    assert KeypointDetector(cfg).crop_net.position
    old = cfg.to_dict()
    del old["crop_position"]  # a checkpoint written before the field: a stage without it
    assert DetectorConfig.from_dict(old).crop_position is False


def test_weights_with_a_stage_told_its_positions_fine_tune_a_stage_without_as_a_fresh_one(tmp_path):
    """A crop.pt whose stage reads crop positions into a model whose stage does not (or the other
    way round, or at another crop side): the whole stage starts fresh, not its hidden layer alone
    under a trained output layer; the detector's tensors are the checkpoint's; a note says why."""
    from omnigen.detector.model.checkpoint import load_pretrained, save_checkpoint
    from omnigen.taxonomy import load_taxonomy

    torch.manual_seed(0)
    fine = load_taxonomy("fine")
    cfg = DetectorConfig(num_classes=12, kpt_heading=True, heading_crop=32, crop_position=True, **TINY)
    src = KeypointDetector(cfg)
    path = tmp_path / "where.pt"
    save_checkpoint(path, {"config": cfg.to_dict(), "model": src.state_dict(), "classes": list(fine.classes)})
    for mine in (dict(heading_crop=32), dict(heading_crop=48, crop_position=True)):
        torch.manual_seed(1)
        model = KeypointDetector(DetectorConfig(num_classes=12, kpt_heading=True, **mine, **TINY))
        fresh = {k: v.clone() for k, v in model.state_dict().items()}
        notes = load_pretrained(model, path, fine)
        assert len(notes) == 1 and "told where its crops were cut" in notes[0]
        for k, v in model.state_dict().items():
            want = fresh[k] if k.startswith("crop_net.") else src.state_dict()[k]
            assert torch.equal(v, want), k
    same = KeypointDetector(cfg)
    assert load_pretrained(same, path, fine) == []  # the same stage: every tensor loads
    assert all(torch.equal(v, src.state_dict()[k]) for k, v in same.state_dict().items())


def test_the_mirror_average_of_a_positioned_stage_is_that_of_the_mirrored_image():
    """Prediction averages each crop's outputs with its mirror image's, told the mirrored position:
    exactly what the net gives for the mirrored image's crop at the mirrored box, mapped back."""
    from omnigen.detector.model.crop_stage import MIRROR_HEADING, crop_position

    torch.manual_seed(0)
    net = CropNet(32, width=8, position=True).eval()
    with torch.no_grad():
        net.hidden[0].weight[:, -3:] *= 50  # a wrong position would show
    image = torch.rand(1, 3, 48, 80)
    boxes = torch.tensor([[5.0, 6.0, 30.0, 40.0], [50.0, 10.0, 75.0, 30.0]])
    index = torch.zeros(2, dtype=torch.long)
    with torch.no_grad():
        h, t, _ = crop_outputs(net, image, index, boxes, 32, mirror=True)
        h1, t1, _ = crop_outputs(net, image, index, boxes, 32)
        mirrored = torch.stack([79.0 - boxes[:, 2], boxes[:, 1], 79.0 - boxes[:, 0], boxes[:, 3]], 1)
        flipped = image.flip(-1)
        h2, t2, _ = split_outputs(net(crop_boxes(flipped, index, mirrored, 32), crop_position(mirrored, torch.tensor([48, 80]))))
    assert torch.allclose(t, (t1 + mirror_corners(t2)) / 2, atol=1e-5)
    assert torch.allclose(h, (h1 + h2 * torch.tensor(MIRROR_HEADING)) / 2, atol=1e-5)


def test_the_crop_nets_pooling_is_max_pool2d_in_value_in_eval_and_is_it_in_training():
    from omnigen.detector.model.crop_stage import MaxPool2

    x = torch.randn(3, 5, 8, 12)
    x[0, 0, :4, :4] = 1.0  # ties, as flat image regions give
    pool = MaxPool2()
    assert torch.equal(pool.eval()(x), torch.nn.functional.max_pool2d(x, 2))
    a, b = x.clone().requires_grad_(), x.clone().requires_grad_()
    pool.train()(a).sum().backward()
    torch.nn.functional.max_pool2d(b, 2).sum().backward()
    assert torch.equal(a.grad, b.grad)  # training's gradient is max_pool2d's, ties and all
