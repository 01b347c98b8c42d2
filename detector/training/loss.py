"""The detector's training loss: box (CIoU + DFL), class (BCE), keypoints (the design's OKS loss) and visibility.

Scaling: every part is an *intensive* quantity, a mean over the batch's positives (box, DFL and
class are normalised by the sum of the target scores, the keypoint loss by the number of positive
anchor-object pairs, the visibility loss by the number of labelled corners). The total is the sum
of the gained parts, NOT multiplied by the batch size as Ultralytics does: doubling the batch
leaves the loss and the gradient scale unchanged, so the learning rate does not depend on the
batch size (and per-GPU losses under data parallelism average to the same value).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
import torch.nn.functional as F

from omnigen.detector.training.assign import TaskAlignedAssigner
from omnigen.detector.model.boxes import bbox2dist, box_area, box_ciou
from omnigen.detector.model.crop_stage import to_crop_units
from omnigen.detector.model.heading import heading_loss, image_heading
from omnigen.detector.model.outputs import REG_MAX, HeadOutput, decode_boxes, head_keypoints
from omnigen.conventions import NUM_KEYPOINTS, TURN_IDX

OKS_SIGMA = 0.125
"""sigma_j of the design's keypoint loss, the same for all eight corners."""

OKS_EPS = 1e-9


@dataclass
class LossGains:
    """Weights of the loss parts in the total.

    box, dfl and cls are those of YOLOv8 (7.5, 1.5, 0.5). The keypoint loss is the design's,
    whose kernel 2 sigma^2 a is 4x narrower than Ultralytics' 8 sigma^2 a: near convergence its
    gradient is 4x stronger (which alone would call for Ultralytics' 12 / 4 = 3), while far from
    the target it saturates sooner and pulls less; kpt = 6.0 sits between the two. kvis = 1.0 as
    Ultralytics' kobj. These are a reasoned starting point, to be checked on the overfit test and
    real data, not the result of a sweep.
    """

    box: float = 7.5
    dfl: float = 1.5
    cls: float = 0.5
    kpt: float = 6.0
    kvis: float = 1.0
    kpt_l1: float = 0.0  # the scale-free L1 corner term (keypoint_l1_loss); 0 leaves the design's loss alone
    # a heading-aware head's OKS loss in the labelled order beside the one up to the turn: a weak pull
    # that makes the branch's own choice of order the labelled one wherever the image tells the
    # front (turn_targets); 0: the branch picks an order freely
    kpt_labelled: float = 0.0
    heading: float = 1.0  # 1 - cosine of a heading-aware head's image heading (heading.py); no term without one
    heading_crop: float = 1.0  # 1 - cosine of a crop-stage model's crop headings (crop_stage.py); no term without one
    crop_corners: float = 1.0  # L1 of a crop-stage model's crop corners, in crop units (crop_stage.py); no term without one
    # cross-entropy of a class-naming crop stage's class logits (crop_stage.py); no term without one.
    # 0.5 as the head's own class term: a starting point, not a sweep
    crop_cls: float = 0.5


PARTS = ("box", "dfl", "cls", "kpt", "kvis", "kpt_l1", "kpt_labelled", "heading", "heading_crop", "crop_corners",
         "crop_cls")

_TURN = list(TURN_IDX)


def oks_keypoint_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor, area: torch.Tensor,
                      sigma: float = OKS_SIGMA, eps: float = OKS_EPS) -> torch.Tensor:
    """The design's keypoint loss L = 1/N sum_i f_i sum_j (1 - exp(-d_ij / (2 sigma^2 a_i + eps))) m_ij.

    pred, gt (N, K, 2) pixels; mask (N, K) bool (m_ij, labelled corner); area (N,) box areas a_i in
    pixels^2; d_ij squared distance; f_i = 1 / sum_j m_ij. Instances without a labelled corner are
    left out of N; with none left the loss is 0 (still attached to `pred`, so backward works).
    Masked corners contribute neither value nor gradient, even when their gt is NaN or inf.
    """
    if pred.shape != gt.shape or pred.shape[:-1] != mask.shape or pred.shape[:1] != area.shape:
        raise ValueError(f"oks_keypoint_loss: shapes pred {tuple(pred.shape)}, gt {tuple(gt.shape)}, "
                         f"mask {tuple(mask.shape)}, area {tuple(area.shape)} do not match (N, K, 2)/(N, K)/(N,)")
    mask = mask.bool()
    gt = torch.where(mask[..., None], gt, pred.detach())  # masked corners: zero distance, no NaN leaks
    d = (pred - gt).pow(2).sum(-1)
    e = d / (2 * sigma**2 * area[:, None] + eps)
    m = mask.to(pred.dtype)
    labelled = m.sum(1)
    keep = labelled > 0
    per_instance = ((1 - torch.exp(-e)) * m).sum(1) / labelled.clamp(min=1)
    # a division, not a count read back: no host-device synchronisation in the training step
    return (per_instance * keep).sum() / keep.sum().clamp(min=1)


def keypoint_l1_loss(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor, area: torch.Tensor) -> torch.Tensor:
    """Mean over instances of the mean labelled corner's L1 error in units of sqrt(box area).

    Why beside the OKS loss: the OKS kernel's slope vanishes for corners far from their target
    (at 0.7 sqrt(a) with sigma 0.25 it pulls exp(-3.9) = 2% as hard as at its peak), so early in
    training, and on objects the model has the layout of wrong (a car seen turned 180 degrees), the
    corners get almost no pull. The L1 term pulls every corner equally hard wherever it is, and,
    normalised by the object's size like OKS, weighs a 10-pixel pedestrian as much as a bus.
    Same shapes and masking as oks_keypoint_loss.
    """
    mask = mask.bool()
    gt = torch.where(mask[..., None], gt, pred.detach())
    err = (pred - gt).abs().sum(-1) / area.clamp(min=1.0).sqrt()[:, None]
    m = mask.to(pred.dtype)
    labelled = m.sum(1)
    keep = labelled > 0
    per_instance = (err * m).sum(1) / labelled.clamp(min=1)
    return (per_instance * keep).sum() / keep.sum().clamp(min=1)


def turn_targets(pred: torch.Tensor, gt: torch.Tensor, mask: torch.Tensor, area: torch.Tensor) -> torch.Tensor:
    """(N,) bool: the prediction's corners fit the object turned 180 degrees better than as labelled.

    Why a heading-aware head learns corners this way: a cuboid turned 180 degrees about its vertical
    axis occupies the same space, so the eight projected points are the same set and only their
    labels (front/rear) change. Where the image does not say which end is the front (a boxy van,
    a car seen from above, a low-resolution aerial view), a loss that compares corner k with
    corner k drives the branch towards the mean of the two labellings: a collapsed layout that fits
    neither (measured: predicted layouts at about half the true spread). Regressing the corners up
    to the turn (the order that fits the prediction better, its target) keeps the layouts sharp;
    which end is the front is left to the image heading (heading.py), which can be unsure without
    blurring the geometry. The fit is the scale-free L1 distance, mean over the corners labelled in
    each order (it stays informative where the OKS kernel saturates).
    """
    turned_gt, turned_mask = gt[:, _TURN], mask[:, _TURN]

    def mean_err(g: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
        g = torch.where(m[..., None], g, pred)
        err = (pred - g).abs().sum(-1) * m
        return err.sum(1) / m.sum(1).clamp(min=1) / area.clamp(min=1.0).sqrt()

    return mean_err(turned_gt, turned_mask.bool()) < mean_err(gt, mask.bool())


@dataclass
class PaddedTargets:
    """The batch's objects laid out per image, (B, M) with M the most objects of one image."""

    labels: torch.Tensor  # (B, M) long
    boxes: torch.Tensor  # (B, M, 4)
    mask: torch.Tensor  # (B, M) bool, False on padding
    index: torch.Tensor  # (B, M) long row in the flat targets, -1 on padding


def pad_targets(targets: dict[str, torch.Tensor], batch_size: int) -> PaddedTargets:
    """Flat (M,) targets with batch_idx -> per-image padded tensors, keeping each image's object order."""
    batch_idx = targets["batch_idx"].long()
    device = batch_idx.device
    counts = torch.bincount(batch_idx, minlength=batch_size)
    width = int(counts.max()) if batch_idx.numel() else 0
    order = torch.sort(batch_idx, stable=True).indices
    image = batch_idx[order]
    offsets = torch.cumsum(counts, 0) - counts
    slot = torch.arange(len(order), device=device) - offsets[image]
    index = torch.full((batch_size, width), -1, dtype=torch.long, device=device)
    index[image, slot] = order
    mask = index >= 0
    safe = index.clamp(min=0)
    boxes = targets["bboxes"].float()
    labels = targets["cls"].long()
    if boxes.shape[0] == 0:  # nothing to gather from
        return PaddedTargets(labels=torch.zeros_like(index), boxes=torch.zeros(batch_size, width, 4, device=device),
                             mask=mask, index=index)
    return PaddedTargets(labels=labels[safe] * mask, boxes=boxes[safe] * mask[..., None], mask=mask, index=index)


def check_targets(targets: dict[str, torch.Tensor], batch_size: int, num_classes: int) -> None:
    """Clear errors for malformed targets, naming the field."""
    shapes = {"batch_idx": (), "cls": (), "bboxes": (4,), "keypoints": (NUM_KEYPOINTS, 2),
              "kpt_mask": (NUM_KEYPOINTS,), "kpt_visible": (NUM_KEYPOINTS,)}
    missing = [k for k in shapes if k not in targets]
    if missing:
        raise KeyError(f"DetectionLoss: targets lack field(s) {missing}")
    m = targets["batch_idx"].shape[0]
    for key, tail in shapes.items():
        shape = tuple(targets[key].shape)
        if shape != (m, *tail):
            raise ValueError(f"DetectionLoss: targets['{key}'] has shape {shape}, expected {(m, *tail)}")
    if m:
        # the four bounds read back in one transfer: a synchronisation per step, not four
        b, c = targets["batch_idx"], targets["cls"]
        b_min, b_max, c_min, c_max = torch.stack([b.min(), b.max(), c.min(), c.max()]).tolist()
        if b_min < 0 or b_max >= batch_size:
            raise ValueError(f"DetectionLoss: targets['batch_idx'] outside 0..{batch_size - 1}")
        if c_min < 0 or c_max >= num_classes:
            raise ValueError(f"DetectionLoss: targets['cls'] outside 0..{num_classes - 1}")


class DetectionLoss:
    """Loss of a batch: (total, parts), parts as detached 0-dim tensors. See the module docstring
    for the scaling.

    `strides` is accepted for the interface's sake; the anchors' strides come with the HeadOutput.
    `kpt_sigma` is the design's 0.125 by default. Its kernel is narrow: a corner more than about
    5 sigma sqrt(a) from its prediction (e.g. the far corners seen from the anchor at the start of
    training: d / a ~ 0.5 gives exp(-16)) gets almost no gradient. A trainer may widen sigma during
    warm-up (set the attribute) and return to the design's value; the default is what is reported.
    """

    def __init__(self, num_classes: int, strides=None, gains: LossGains | None = None,
                 assigner: TaskAlignedAssigner | None = None, kpt_sigma: float = OKS_SIGMA):
        if isinstance(strides, LossGains):  # DetectionLoss(nc, LossGains(...)) positionally
            strides, gains = None, strides
        self.num_classes = num_classes
        self.strides = None if strides is None else list(strides)
        self.gains = gains or LossGains()
        self.assigner = assigner or TaskAlignedAssigner()
        self.kpt_sigma = kpt_sigma
        # a heading-aware head's corners are compared in the labelled order until the trainer frees
        # them (TrainConfig.kpt_turn_start): the branch first learns the labelled order, so that its
        # later choice between the two orders starts from the true heading wherever the image shows it
        self.turn_free = True

    def __call__(self, out: HeadOutput, targets: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, float]]:
        b, nc, a = out.cls.shape
        if nc != self.num_classes:
            raise ValueError(f"DetectionLoss: head gives {nc} classes, loss built for {self.num_classes}")
        check_targets(targets, b, nc)
        device = out.cls.device
        targets = {k: v.to(device) for k, v in targets.items()}
        # Float32 whatever the autocast dtype: IoU^6 and exp(-e) underflow in half precision.
        out = HeadOutput(box=out.box.float(), cls=out.cls.float(), kpt=out.kpt.float(),
                         anchors=out.anchors.float(), strides=out.strides.float(), kpt_mode=out.kpt_mode,
                         heading=None if out.heading is None else out.heading.float(),
                         crop_heading=None if out.crop_heading is None else out.crop_heading.float(),
                         crop_corners=None if out.crop_corners is None else out.crop_corners.float(),
                         crop_logits=None if out.crop_logits is None else out.crop_logits.float(),
                         crop_rows=out.crop_rows,
                         crop_boxes=None if out.crop_boxes is None else out.crop_boxes.float())
        gt = pad_targets(targets, b)

        cls_logits = out.cls.transpose(1, 2)  # (B, A, nc)
        pred_boxes = decode_boxes(out.box, out.anchors, out.strides).transpose(1, 2)  # (B, A, 4)
        asg = self.assigner(cls_logits.detach().sigmoid(), pred_boxes.detach(), out.anchors,
                            gt.labels, gt.boxes.to(pred_boxes.dtype), gt.mask)
        score_sum = asg.target_scores.sum().clamp(min=1)

        cls_loss = F.binary_cross_entropy_with_logits(cls_logits, asg.target_scores.to(cls_logits.dtype),
                                                      reduction="sum") / score_sum
        fg = asg.fg_mask
        bi, ai = fg.nonzero(as_tuple=True)
        weight = asg.target_scores[bi, ai].sum(-1)
        target_boxes = asg.target_boxes[bi, ai]
        box_loss = ((1 - box_ciou(pred_boxes[bi, ai], target_boxes)) * weight).sum() / score_sum
        dfl_loss = self._dfl(out, bi, ai, target_boxes, weight) / score_sum

        obj = gt.index[bi, asg.target_gt_idx[bi, ai]]  # (N,) rows of the flat targets
        # 'box' mode decodes corners in units of the anchor's own box, detached: corners train the
        # keypoint branch, not the box
        kpts = head_keypoints(out, pred_boxes.detach().transpose(1, 2))[bi, :, :, ai]  # (N, K, 3)
        kmask = targets["kpt_mask"].bool()[obj]
        area = box_area(targets["bboxes"].to(kpts.dtype)[obj])
        kpt_gt = targets["keypoints"].to(kpts.dtype)[obj]
        vis_gt = targets["kpt_visible"].to(kpts.dtype)[obj]
        kpt_labelled = heading_loss_ = kpts.new_zeros(())
        if out.heading is not None:
            if self.gains.kpt_labelled:
                kpt_labelled = oks_keypoint_loss(kpts[..., :2], kpt_gt, kmask, area, sigma=self.kpt_sigma)
            # the target is the labelled corners' own image heading: fixed, whatever order the
            # branch predicts
            heading_loss_ = heading_loss(out.heading[bi, :, ai], image_heading(kpt_gt, area, kmask))
            turned = turn_targets(kpts[..., :2].detach(), kpt_gt, kmask, area) if self.turn_free \
                else torch.zeros(len(obj), dtype=torch.bool, device=device)  # (N,)
            kpt_gt = torch.where(turned[:, None, None], kpt_gt[:, _TURN], kpt_gt)
            kmask = torch.where(turned[:, None], kmask[:, _TURN], kmask)
            vis_gt = torch.where(turned[:, None], vis_gt[:, _TURN], vis_gt)
        crop_loss = corner_loss = crop_cls = kpts.new_zeros(())
        if out.crop_logits is not None and len(out.crop_rows):
            # each crop is one labelled object: a softmax over the classes, not the head's per-class BCE
            crop_cls = F.cross_entropy(out.crop_logits, targets["cls"].long()[out.crop_rows])
        if out.crop_corners is not None:
            # the corners in front of the camera, in the units of the crop each was cut from (the
            # targets' box, moved), as the stage predicts them
            rows = out.crop_rows
            target = to_crop_units(targets["keypoints"].to(kpts.dtype)[rows], out.crop_boxes)
            cmask = targets["kpt_mask"].bool()[rows]
            corner_loss = ((out.crop_corners - target.nan_to_num()).abs().sum(-1) * cmask).sum() / cmask.sum().clamp(min=1)
        if out.crop_heading is not None:
            # the crops' target is the one the head's channels learn: the labelled corners' image heading
            rows = out.crop_rows
            crop_loss = heading_loss(out.crop_heading, image_heading(
                targets["keypoints"].to(kpts.dtype)[rows], box_area(targets["bboxes"].to(kpts.dtype)[rows]),
                targets["kpt_mask"].bool()[rows]))
        kpt_loss = oks_keypoint_loss(kpts[..., :2], kpt_gt, kmask, area, sigma=self.kpt_sigma)
        kpt_l1 = keypoint_l1_loss(kpts[..., :2], kpt_gt, kmask, area)
        vis_target = torch.where(kmask, vis_gt, torch.zeros_like(kpts[..., 2]))
        kvis_loss = (F.binary_cross_entropy_with_logits(kpts[..., 2], vis_target, reduction="none") * kmask
                     ).sum() / kmask.sum().clamp(min=1)

        parts_t = {"box": box_loss, "dfl": dfl_loss, "cls": cls_loss, "kpt": kpt_loss, "kvis": kvis_loss, "kpt_l1": kpt_l1,
                   "kpt_labelled": kpt_labelled, "heading": heading_loss_, "heading_crop": crop_loss,
                   "crop_corners": corner_loss, "crop_cls": crop_cls}
        gains = asdict(self.gains)
        total = sum(gains[k] * parts_t[k] for k in PARTS)
        # detached 0-dim tensors, not floats: a float() per part would wait for the device six
        # times a step; the trainer sums them where they are (train_step.PartSums) and reads once
        return total, {k: v.detach() for k, v in parts_t.items()}

    @staticmethod
    def _dfl(out: HeadOutput, bi, ai, target_boxes, weight) -> torch.Tensor:
        """Distribution focal loss: cross-entropy towards the two bins around each side's distance
        (in strides), weighted by closeness; summed over positives with the assignment weight."""
        b, _, a = out.box.shape
        logits = out.box.reshape(b, 4, REG_MAX, a)[bi, :, :, ai]  # (N, 4, R)
        stride = out.strides[ai][:, None]
        target = bbox2dist(out.anchors[ai] / stride, target_boxes / stride, REG_MAX - 1)  # (N, 4)
        left = target.long()
        w_right = target - left
        logp = logits.log_softmax(-1)
        ce_left = -logp.gather(-1, left[..., None]).squeeze(-1)
        ce_right = -logp.gather(-1, (left + 1)[..., None]).squeeze(-1)
        per_side = ce_left * (1 - w_right) + ce_right * w_right
        return (per_side.mean(-1) * weight).sum()
