"""Label assignment and loss of the detector: the design's keypoint formula, the assigner, robustness."""

from __future__ import annotations

import math

import pytest
import torch

from omnigen.detector.training.assign import TaskAlignedAssigner
from omnigen.detector.model.boxes import bbox2dist, box_area, box_ciou, box_iou, box_iou_pairwise, dist2bbox
from omnigen.detector.training.loss import PARTS, DetectionLoss, LossGains, keypoint_l1_loss, oks_keypoint_loss
from omnigen.detector.model.outputs import REG_MAX, HeadOutput, decode_keypoints, make_anchors

SIGMA = 0.125


def hand_oks(pred, gt, mask, area, kernel):
    """The formula in plain Python: 1/N sum_i 1/n_i sum_j (1 - exp(-d_ij / (kernel * sigma^2 * a_i + eps))) m_ij."""
    total, n = 0.0, 0
    for p_i, g_i, m_i, a_i in zip(pred, gt, mask, area):
        labelled = sum(m_i)
        if labelled == 0:
            continue
        s = 0.0
        for (px, py), (gx, gy), m in zip(p_i, g_i, m_i):
            if m:
                d = (px - gx) ** 2 + (py - gy) ** 2
                s += 1 - math.exp(-d / (kernel * SIGMA**2 * a_i + 1e-9))
        total += s / labelled
        n += 1
    return total / n


@pytest.fixture
def oks_case():
    g = torch.Generator().manual_seed(0)
    gt = torch.rand(4, 8, 2, generator=g, dtype=torch.float64) * 100
    pred = gt + torch.randn(4, 8, 2, generator=g, dtype=torch.float64) * torch.tensor([2.0, 5.0, 20.0, 3.0]
                                                                                      ).view(4, 1, 1).double()
    mask = torch.ones(4, 8, dtype=torch.bool)
    mask[1, [0, 3, 5]] = False  # a truncated object
    mask[2, :] = False  # nothing labelled: left out of N
    mask[3, 1:] = False  # a single labelled corner
    area = torch.tensor([900.0, 2500.0, 400.0, 64.0], dtype=torch.float64)
    return pred, gt, mask, area


def test_oks_loss_matches_hand_computation(oks_case):
    pred, gt, mask, area = oks_case
    expected = hand_oks(pred.tolist(), gt.tolist(), mask.tolist(), area.tolist(), kernel=2)
    got = oks_keypoint_loss(pred, gt, mask, area)
    assert float(got) == pytest.approx(expected, rel=1e-9)
    ultralytics_like = hand_oks(pred.tolist(), gt.tolist(), mask.tolist(), area.tolist(), kernel=8)
    assert abs(float(got) - ultralytics_like) > 1e-3  # the 8 sigma^2 variant is a different loss


def test_oks_loss_no_labelled_corner_is_zero_with_grad():
    pred = torch.randn(3, 8, 2, requires_grad=True)
    loss = oks_keypoint_loss(pred, torch.zeros(3, 8, 2), torch.zeros(3, 8, dtype=torch.bool), torch.ones(3))
    loss.backward()
    assert float(loss.detach()) == 0.0 and pred.grad is not None and torch.all(pred.grad == 0)
    empty = torch.zeros(0, 8, 2, requires_grad=True)
    none = oks_keypoint_loss(empty, empty.detach(), torch.zeros(0, 8, dtype=torch.bool), torch.zeros(0))
    assert float(none.detach()) == 0


def test_masked_corners_have_no_influence(oks_case):
    pred, gt, mask, area = oks_case
    pred = pred.clone().requires_grad_(True)
    gt = gt.clone().requires_grad_(True)
    loss = oks_keypoint_loss(pred, gt, mask, area)
    loss.backward()
    masked = ~mask
    assert torch.all(pred.grad[masked] == 0) and torch.all(gt.grad[masked] == 0)
    assert torch.any(pred.grad[mask] != 0)
    wild = gt.detach().clone()
    wild[masked] = float("nan")
    wild[1, 0] = 1e9
    assert float(oks_keypoint_loss(pred.detach(), wild, mask, area)) == pytest.approx(float(loss.detach()))


def test_box_utilities():
    a = torch.tensor([[0.0, 0, 10, 10], [0, 0, 4, 4]])
    b = torch.tensor([[5.0, 0, 15, 10], [10, 10, 14, 14]])
    assert torch.allclose(box_iou(a, b), torch.tensor([50 / 150, 0.0]))
    assert torch.allclose(box_iou_pairwise(a, b)[0], torch.tensor([50 / 150, 0.0]))
    assert torch.allclose(box_ciou(a, a), torch.ones(2), atol=1e-6)
    assert float(box_ciou(a, b)[1]) < 0  # disjoint: CIoU still ranks by centre distance
    anchors = torch.tensor([[5.0, 5.0], [2.0, 2.0]])
    assert torch.allclose(dist2bbox(bbox2dist(anchors, a, 100), anchors), a)


def test_assigner_hand_case():
    """Two overlapping objects on an 8x8 grid of stride-8 anchors (centres 4, 12, ..., 60)."""
    anchors, _ = make_anchors([(8, 8)], [8])
    a = anchors.shape[0]

    def idx(x, y):
        return int(((anchors[:, 0] == x) & (anchors[:, 1] == y)).nonzero())

    pd_boxes = torch.cat([anchors - 4, anchors + 4], 1)  # each anchor predicts its own cell
    pd_boxes[idx(12, 12)] = torch.tensor([8.0, 8, 40, 24])  # ... except one that predicts object B exactly
    scores = torch.full((a, 2), 0.5)
    scores[idx(20, 12), 1], scores[idx(28, 12), 1], scores[idx(36, 12), 1] = 0.9, 0.8, 0.7
    gt_boxes = torch.tensor([[[0.0, 0, 16, 16], [8, 8, 40, 24]], [[0, 0, 0, 0], [0, 0, 0, 0]]])
    gt_labels = torch.tensor([[0, 1], [0, 0]])
    gt_mask = torch.tensor([[True, True], [False, False]])  # image 1 has no objects
    res = TaskAlignedAssigner(topk=4)(torch.stack([scores, scores]), torch.stack([pd_boxes, pd_boxes]), anchors,
                                      gt_labels, gt_boxes, gt_mask)
    # A's candidates: (4,4) (12,4) (4,12) (12,12); B's: x in 12..36, y in 12, 20. (12,12) is in both
    # top-4s and goes to B, whose box its prediction matches; B's other positives are its best scores.
    want_a = {idx(4, 4), idx(12, 4), idx(4, 12)}
    want_b = {idx(12, 12), idx(20, 12), idx(28, 12), idx(36, 12)}
    fg = set(res.fg_mask[0].nonzero().flatten().tolist())
    assert fg == want_a | want_b
    assert not res.fg_mask[1].any()
    assert all(int(res.target_gt_idx[0, i]) == 0 for i in want_a)
    assert all(int(res.target_gt_idx[0, i]) == 1 for i in want_b)
    assert torch.equal(res.target_boxes[0, idx(12, 12)], gt_boxes[0, 1])
    # Normalised scores: an object's best anchor gets its best IoU; A's three tie at IoU 64/256.
    assert float(res.target_scores[0, idx(12, 12), 1]) == pytest.approx(1.0, abs=1e-6)
    for i in want_a:
        assert res.target_scores[0, i].tolist() == pytest.approx([0.25, 0.0], abs=1e-6)
    assert float(res.target_scores[1].abs().sum()) == 0


def _anchors():
    return make_anchors([(8, 8), (4, 4), (2, 2)], [8, 16, 32])


def _head(b, nc, a, seed=0, requires_grad=True, kpt_mode="anchor"):
    g = torch.Generator().manual_seed(seed)
    anchors, strides = _anchors()
    box = (torch.randn(b, 4 * REG_MAX, a, generator=g) * 0.1).requires_grad_(requires_grad)
    cls = (torch.randn(b, nc, a, generator=g) * 0.1 - 4).requires_grad_(requires_grad)
    kpt = (torch.randn(b, 24, a, generator=g) * 0.1).requires_grad_(requires_grad)
    return HeadOutput(box=box, cls=cls, kpt=kpt, anchors=anchors, strides=strides, kpt_mode=kpt_mode)


def _targets():
    boxes = torch.tensor([[4.0, 6, 30, 40], [30, 20, 60, 50], [10, 10, 50, 30]])
    g = torch.Generator().manual_seed(1)
    kpts = boxes[:, None, :2] + torch.rand(3, 8, 2, generator=g) * (boxes[:, None, 2:] - boxes[:, None, :2])
    kpts[2, 7] = torch.tensor([-6.0, 70.0])  # outside the image, in front of the camera: still a target
    mask = torch.ones(3, 8, dtype=torch.bool)
    mask[1, 4:] = False
    visible = torch.ones(3, 8)
    visible[0, 2] = 0.0
    visible[2, 7] = 0.0
    return {"batch_idx": torch.tensor([0, 0, 1]), "cls": torch.tensor([0, 2, 1]), "bboxes": boxes,
            "keypoints": kpts, "kpt_mask": mask, "kpt_visible": visible}


def test_empty_targets_give_finite_loss_and_grads():
    a = _anchors()[0].shape[0]
    out = _head(2, 3, a)
    empty = {"batch_idx": torch.zeros(0, dtype=torch.long), "cls": torch.zeros(0, dtype=torch.long),
             "bboxes": torch.zeros(0, 4), "keypoints": torch.zeros(0, 8, 2),
             "kpt_mask": torch.zeros(0, 8, dtype=torch.bool), "kpt_visible": torch.zeros(0, 8)}
    total, parts = DetectionLoss(3)(out, empty)
    total.backward()
    assert torch.isfinite(total) and set(parts) == set(PARTS)
    assert parts["box"] == parts["kpt"] == 0.0 and parts["cls"] > 0
    assert torch.all(torch.isfinite(out.cls.grad)) and out.cls.grad.abs().sum() > 0
    # One image with objects, one without.
    out = _head(2, 3, a)
    t = {k: v[:2] for k, v in _targets().items()}
    total, parts = DetectionLoss(3)(out, t)
    total.backward()
    assert torch.isfinite(total) and all(math.isfinite(v) for v in parts.values()) and parts["kpt"] > 0
    assert all(torch.all(torch.isfinite(p.grad)) for p in (out.box, out.cls, out.kpt))


def test_loss_invariant_to_gt_order():
    a = _anchors()[0].shape[0]
    out = _head(2, 3, a, requires_grad=False)
    t = _targets()
    perm = torch.tensor([2, 1, 0])
    total, parts = DetectionLoss(3)(out, t)
    total_p, parts_p = DetectionLoss(3)(out, {k: v[perm] for k, v in t.items()})
    assert float(total_p) == pytest.approx(float(total), rel=1e-6)
    assert {k: float(v) for k, v in parts_p.items()} == pytest.approx({k: float(v) for k, v in parts.items()}, rel=1e-6)


def test_masked_keypoints_do_not_change_detection_loss():
    a = _anchors()[0].shape[0]
    out = _head(2, 3, a, requires_grad=False)
    t = _targets()
    total, _ = DetectionLoss(3)(out, t)
    t["keypoints"][1, 4:] = float("nan")
    t["kpt_visible"][1, 4:] = 0.5
    total_nan, _ = DetectionLoss(3)(out, t)
    assert float(total_nan) == pytest.approx(float(total), rel=1e-6)


def test_bad_targets_name_the_field():
    a = _anchors()[0].shape[0]
    t = _targets()
    t["kpt_mask"] = t["kpt_mask"][:, :4]
    with pytest.raises(ValueError, match="kpt_mask"):
        DetectionLoss(3)(_head(2, 3, a, requires_grad=False), t)


def test_sigma_warmup_reaches_far_and_out_of_image_corners():
    """The design's narrow kernel gives ~no gradient to corners far from their prediction; widening
    sigma for a warm-up (then back to 0.125) lets every labelled corner, including one outside the
    image, be learned."""
    torch.manual_seed(0)
    a = _anchors()[0].shape[0]
    out = _head(2, 3, a)
    opt = torch.optim.Adam([out.box, out.cls, out.kpt], lr=0.05)
    loss_fn = DetectionLoss(3)
    t = _targets()
    for step in range(120):
        loss_fn.kpt_sigma = 0.5 if step < 60 else 0.125
        opt.zero_grad()
        total, parts = loss_fn(out, t)
        total.backward()
        opt.step()
    assert loss_fn.kpt_sigma == 0.125 and parts["kpt"] < 0.02


def _brute_assign(scores, boxes, anchors, labels, gts, mask, topk, alpha=0.5, beta=6.0):
    """Plain-Python reference: {(image, anchor): object slot}."""
    def iou(p, q):
        iw = max(0.0, min(p[2], q[2]) - max(p[0], q[0]))
        ih = max(0.0, min(p[3], q[3]) - max(p[1], q[1]))
        inter = iw * ih
        return inter / ((p[2] - p[0]) * (p[3] - p[1]) + (q[2] - q[0]) * (q[3] - q[1]) - inter + 1e-7)

    claims = {}
    for b in range(len(gts)):
        for m, g in enumerate(gts[b]):
            if not mask[b][m]:
                continue
            cand = [i for i, (x, y) in enumerate(anchors) if g[0] < x < g[2] and g[1] < y < g[3]]
            ranked = sorted(cand, key=lambda i: -(scores[b][i][labels[b][m]] ** alpha * iou(g, boxes[b][i]) ** beta))
            for i in ranked[:topk]:
                claims.setdefault((b, i), []).append((iou(g, boxes[b][i]), m))
    return {k: max(v)[1] for k, v in claims.items()}


def test_assigner_gives_objects_smaller_than_a_cell_their_nearest_anchor():
    """A 3x3 px object between anchor centres (stride 8: centres at 4, 12, ...) still gets a positive."""
    anchors, _ = make_anchors([(8, 8)], [8])
    a = anchors.shape[0]
    pd_boxes = torch.cat([anchors - 4, anchors + 4], 1)
    gt_boxes = torch.tensor([[[13.5, 5.0, 16.5, 8.0]]])  # centre (15, 6.5): nearest anchor (12, 4)
    res = TaskAlignedAssigner(topk=4)(torch.full((1, a, 1), 0.5), pd_boxes[None], anchors,
                                      torch.tensor([[0]]), gt_boxes, torch.tensor([[True]]))
    fg = res.fg_mask[0].nonzero().flatten().tolist()
    assert len(fg) == 1 and anchors[fg[0]].tolist() == [12.0, 4.0]


def test_assigner_matches_brute_force_reference():
    g = torch.Generator().manual_seed(3)
    anchors, _ = _anchors()
    a = anchors.shape[0]
    xy = torch.rand(2, 4, 2, generator=g) * 40
    gts = torch.cat([xy, xy + 8 + torch.rand(2, 4, 2, generator=g) * 30], -1)
    mask = torch.tensor([[True, True, True, False], [True, True, False, False]])
    labels = torch.randint(0, 3, (2, 4), generator=g)
    centre = anchors + torch.randn(2, a, 2, generator=g) * 4
    half = 4 + torch.rand(2, a, 2, generator=g) * 16
    boxes = torch.cat([centre - half, centre + half], -1)
    scores = torch.rand(2, a, 3, generator=g)
    res = TaskAlignedAssigner(topk=5)(scores, boxes, anchors, labels, gts, mask)
    want = _brute_assign(scores.tolist(), boxes.tolist(), anchors.tolist(), labels.tolist(), gts.tolist(),
                         mask.tolist(), topk=5)
    got = {(b, i): int(res.target_gt_idx[b, i]) for b, i in res.fg_mask.nonzero().tolist()}
    assert len(want) > 10 and got == want


def test_l1_loss_matches_hand_computation(oks_case):
    pred, gt, mask, area = oks_case
    expected, n = 0.0, 0
    for p_i, g_i, m_i, a_i in zip(pred.tolist(), gt.tolist(), mask.tolist(), area.tolist()):
        if not any(m_i):
            continue
        errs = [(abs(px - gx) + abs(py - gy)) / math.sqrt(a_i) for (px, py), (gx, gy), m in zip(p_i, g_i, m_i) if m]
        expected += sum(errs) / len(errs)
        n += 1
    assert float(keypoint_l1_loss(pred, gt, mask, area)) == pytest.approx(expected / n, rel=1e-9)


def test_l1_term_pulls_corners_the_oks_kernel_has_let_go():
    """A corner 3 sqrt(a) from its target: the OKS loss (sigma 0.25) gives it ~no gradient, the L1 term
    a full one, so only with kpt_l1 > 0 does it move."""
    gt = torch.zeros(1, 8, 2)
    pred = torch.full((1, 8, 2), 30.0, requires_grad=True)
    mask, area = torch.ones(1, 8, dtype=torch.bool), torch.tensor([100.0])
    oks_keypoint_loss(pred, gt, mask, area, sigma=0.25).backward()
    oks_grad = pred.grad.abs().max().item()
    pred.grad = None
    keypoint_l1_loss(pred, gt, mask, area).backward()
    assert oks_grad < 1e-20 < pred.grad.abs().min().item()
    assert pred.grad.abs().min().item() == pytest.approx(1 / (8 * 10))


def test_box_mode_decodes_corners_in_units_of_the_box():
    anchors, strides = _anchors()
    a = anchors.shape[0]
    boxes = torch.zeros(1, 4, a)
    boxes[0, :, 0] = torch.tensor([10.0, 20.0, 50.0, 40.0])  # 40 x 20 around (30, 30)
    kpt = torch.zeros(1, 24, a)
    kpt[0, 0:2, 0] = torch.tensor([0.5, -0.5])  # corner 0: the box's top-right
    kpt[0, 3:5, 0] = torch.tensor([-1.0, 0.0])  # corner 1: half a box left of its left edge
    k = decode_keypoints(kpt, anchors, strides, boxes)
    assert k[0, 0, :2, 0].tolist() == [50.0, 20.0] and k[0, 1, :2, 0].tolist() == [-10.0, 30.0]
    assert k[0, 2, :2, 0].tolist() == [30.0, 30.0]  # raw 0: the box centre
    # a degenerate box still scales the offsets by at least a stride
    assert decode_keypoints(kpt, anchors, strides, torch.zeros(1, 4, a))[0, 1, 0, 0].item() == -strides[0].item()


def _fit(out, loss_fn, params, steps=100):
    """Adam on raw head tensors: (first total, first parts, last total, last parts)."""
    opt = torch.optim.Adam(params, lr=0.05)
    t = _targets()
    first, first_parts = loss_fn(out, t)
    for _ in range(steps):
        opt.zero_grad()
        total, parts = loss_fn(out, t)
        total.backward()
        opt.step()
    return first, first_parts, total, parts


@pytest.mark.parametrize("kpt_mode,kpt_l1", [("anchor", 0.0), ("box", 0.0), ("box", 2.0), ("anchor", 2.0)])
def test_free_head_outputs_learn_the_targets(kpt_mode, kpt_l1):
    """Adam on the raw head tensors (no model) must drive every part of the loss down, in both
    keypoint modes, with and without the L1 term."""
    torch.manual_seed(0)
    a = _anchors()[0].shape[0]
    out = _head(2, 3, a, kpt_mode=kpt_mode)
    first, first_parts, total, parts = _fit(out, DetectionLoss(3, gains=LossGains(kpt_l1=kpt_l1)),
                                            [out.box, out.cls, out.kpt])
    assert float(total.detach()) < 0.2 * float(first.detach())
    assert parts["kpt"] < 0.2 * first_parts["kpt"] and parts["box"] < 0.5 * first_parts["box"]
    if kpt_l1:
        assert parts["kpt_l1"] < 0.3 * first_parts["kpt_l1"]


def test_box_mode_corners_do_not_pull_the_box():
    """In 'box' mode the loss decodes corners on the detached box: the keypoint terms alone give the
    box logits no gradient."""
    a = _anchors()[0].shape[0]
    out = _head(2, 3, a, kpt_mode="box")
    loss_fn = DetectionLoss(3, gains=LossGains(box=0, dfl=0, cls=0, kvis=0, kpt=6.0, kpt_l1=2.0))
    total, _ = loss_fn(out, _targets())
    total.backward()
    assert out.kpt.grad.abs().sum() > 0 and (out.box.grad is None or out.box.grad.abs().sum() == 0)


def test_turn_targets_pick_the_order_the_prediction_fits():
    from omnigen.detector.training.loss import turn_targets
    from omnigen.conventions import TURN_IDX

    t = _targets()
    gt, mask, area = t["keypoints"], t["kpt_mask"], box_area(t["bboxes"])
    assert not turn_targets(gt.clone(), gt, mask, area).any()
    assert turn_targets(gt[:, list(TURN_IDX)], gt, mask, area).all()  # the same points, labelled turned
    # near the turned layout, not on it: still turned; masked corners (object 1's bottom) do not count
    noisy = gt[:, list(TURN_IDX)] + 0.5
    noisy[1, :4] = gt[1, list(TURN_IDX)][:4] + 0.5
    assert turn_targets(noisy, gt, mask, area).tolist() == [True, True, True]


def test_heading_aware_loss_compares_as_labelled_until_freed_then_up_to_the_turn():
    """Until the trainer frees the order (turn_free False: the first schedule.kpt_turn_start of the
    run) a heading-aware head's corners are compared as labelled, so the same points labelled
    turned pay more or less than as labelled; once freed, either labelling pays the same corner
    loss (the heading alone says which face is the front)."""
    from omnigen.conventions import TURN_IDX

    a = _anchors()[0].shape[0]
    loss_fn = DetectionLoss(3, gains=LossGains(box=0, dfl=0, cls=0, kvis=0, kpt=6.0))
    out = _head(2, 3, a)
    out.kpt = out.kpt.detach() * 10  # layouts spread about the anchor: no object near a tie between the two orders
    out.heading = torch.randn(2, 3, a, generator=torch.Generator().manual_seed(3))
    turned = _reordered(out, TURN_IDX)
    freed, freed_t = loss_fn(out, _targets())[1], loss_fn(turned, _targets())[1]
    for part in ("kpt", "kpt_l1"):
        assert float(freed_t[part]) == pytest.approx(float(freed[part]), abs=1e-6)
    loss_fn.turn_free = False
    held, held_t = loss_fn(out, _targets())[1], loss_fn(turned, _targets())[1]
    assert abs(float(held_t["kpt_l1"]) - float(held["kpt_l1"])) > 1e-3
    # freed, each object is compared in the order its corners fit better: never worse than as labelled
    assert float(freed["kpt_l1"]) <= float(held["kpt_l1"]) + 1e-6


def _side_view_corners() -> torch.Tensor:
    """A car seen square from its side, front to the image right, both faces the same size: front
    corners at x 80-84, rear at x 20-24, top y 30, bottom y 60."""
    kp = torch.zeros(8, 2)
    kp[[0, 1, 4, 5], 0] = torch.tensor([80.0, 84, 80, 84])
    kp[[3, 2, 7, 6], 0] = torch.tensor([20.0, 24, 20, 24])
    kp[:4, 1], kp[4:, 1] = 30.0, 60.0
    return kp


def test_image_heading_is_fixed_by_the_labelled_corners_and_flips_with_the_turn():
    from omnigen.conventions import TURN_IDX
    from omnigen.detector.model.heading import image_heading

    kp = _side_view_corners()
    area = torch.tensor(64.0 * 30.0)
    h = image_heading(kp, area)
    assert h.tolist() == pytest.approx([60.0 / math.sqrt(1920.0), 0.0, 0.0], abs=1e-6)  # front to the right, same size
    assert torch.equal(image_heading(kp[list(TURN_IDX)], area), -h)  # the same points, turned: -h
    g = torch.Generator().manual_seed(5)  # exactly, on any layout, masked or not
    xy, areas = torch.rand(500, 8, 2, generator=g) * 300, torch.rand(500, generator=g) * 900 + 1
    m = torch.rand(500, 8, generator=g) > 0.2
    turn = list(TURN_IDX)
    assert torch.equal(image_heading(xy[:, turn], areas, m[:, turn]), -image_heading(xy, areas, m))
    # facing the camera: the front face larger than the rear one -> a positive third component
    near = kp.clone()
    near[[0, 1, 4, 5], 1] = torch.tensor([20.0, 20, 70, 70])
    assert image_heading(near, area)[2] > 0 and image_heading(near[list(TURN_IDX)], area)[2] < 0
    # a face with no labelled corner gives no target; NaN in unlabelled corners does not leak
    mask = torch.ones(8, dtype=torch.bool)
    mask[[0, 1, 4, 5]] = False
    hidden = kp.clone()
    hidden[[0, 1, 4, 5]] = float("nan")
    assert image_heading(hidden, area, mask).tolist() == [0.0, 0.0, 0.0]


def test_heading_loss_is_one_minus_cosine_over_objects_with_a_target():
    from omnigen.detector.model.heading import heading_loss

    target = torch.tensor([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 0.0]])  # the last has no target
    assert float(heading_loss(target * 3, target)) == pytest.approx(0.0, abs=1e-6)
    assert float(heading_loss(-target, target)) == pytest.approx(2.0, abs=1e-6)
    pred = torch.tensor([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [5.0, 5.0, 5.0]])
    assert float(heading_loss(pred, target)) == pytest.approx(0.5, abs=1e-6)  # (1 + 0) / 2


def test_heading_aware_loss_targets_do_not_depend_on_the_predicted_order():
    """The corners' target order is whichever they fit; the heading's target is the labelled
    corners' own: turning the predicted corners leaves the heading loss as it was."""
    from omnigen.conventions import TURN_IDX

    a = _anchors()[0].shape[0]
    loss_fn = DetectionLoss(3, gains=LossGains(box=0, dfl=0, cls=0, kvis=0, kpt=6.0))
    out = _head(2, 3, a)
    out.heading = torch.randn(2, 3, a, generator=torch.Generator().manual_seed(3), requires_grad=True)
    total, parts = loss_fn(out, _targets())
    total.backward()
    assert 0 < parts["heading"] < 2 and out.heading.grad.abs().sum() > 0
    turned = _reordered(out, TURN_IDX)
    _, parts_t = loss_fn(turned, _targets())
    assert parts_t["heading"] == pytest.approx(float(parts["heading"]), abs=1e-6)


def _reordered(out, order):
    from dataclasses import replace

    k = out.kpt.detach().view(out.kpt.shape[0], 8, 3, -1)[:, list(order)].reshape(out.kpt.shape)
    return replace(out, kpt=k, heading=out.heading.detach())


def test_heading_aware_model_decodes_in_the_labelled_order():
    """The heading rides in the keypoint branch's channels 24-26; decode turns the layout wherever
    the layout's own image heading points against the predicted one."""
    from dataclasses import replace

    from omnigen.conventions import TURN_IDX
    from omnigen.detector.model.heading import image_heading
    from omnigen.detector.model.network import DetectorConfig, KeypointDetector
    from omnigen.detector.model.outputs import apply_heading, decode, decode_boxes, head_keypoints

    cfg = DetectorConfig(width=0.0625, depth=0.33, max_channels=64, num_classes=3, kpt_heading=True)
    model = KeypointDetector(cfg).eval()
    with torch.no_grad():
        out = model(torch.rand(1, 3, 64, 64))
        assert out.heading is not None and out.heading.shape == (1, 3, out.cls.shape[2]) and out.kpt.shape[1] == 24
        boxes = decode_boxes(out.box, out.anchors, out.strides)
        k = head_keypoints(out, boxes)
        area = ((boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1])).clamp(min=1.0)
        own = image_heading(k[:, :, :2].permute(0, 3, 1, 2), area).transpose(1, 2)  # (1, 3, A)
        agree, disagree = decode(replace(out, heading=own)), decode(replace(out, heading=-own))
        plain = decode(replace(out, heading=None))
    k_a, k_d, k_p = (t[:, 7:].view(1, 8, 3, -1) for t in (agree, disagree, plain))
    assert torch.equal(k_a, k_p) and torch.equal(k_d, k_p[:, list(TURN_IDX)])
    assert torch.equal(apply_heading(k, own, boxes), k)


def test_free_heading_aware_head_learns_corners_and_heading():
    """Adam on raw head tensors with a heading: corners converge up to the turn and the heading to
    its fixed target."""
    torch.manual_seed(0)
    a = _anchors()[0].shape[0]
    out = _head(2, 3, a, kpt_mode="box")
    out.heading = torch.zeros(2, 3, a).normal_(0, 0.1).requires_grad_(True)
    _, first_parts, _, parts = _fit(out, DetectionLoss(3, gains=LossGains(kpt_l1=2.0)),
                                    [out.box, out.cls, out.kpt, out.heading])
    assert parts["kpt"] < 0.2 * first_parts["kpt"] and parts["heading"] < 0.05
