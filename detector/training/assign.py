"""Task-aligned label assignment (TOOD, Feng et al. 2021, as used by YOLOv8): which anchors learn which object.

An anchor-free head predicts a box and class scores at every anchor; the assigner decides, per
image, which anchors are positives for which ground-truth object and how strongly. It ranks the
anchors of each object by the alignment metric t = s^alpha * IoU^beta, where s is the predicted
score of the object's class and IoU the overlap of the predicted box with the object's box. Using
the prediction itself (not just geometry) makes the anchors that already classify *and* localise
well the positives, so classification and localisation are trained towards the same anchors.

Defaults (those of TOOD / YOLOv8): topk = 10 positives per object at most, alpha = 0.5,
beta = 6.0 (IoU dominates: the score only breaks ties between similarly localised anchors).
Candidates are the anchors whose centre lies strictly inside the object's box; an anchor claimed
by several objects keeps the one its predicted box overlaps most. Target scores are the
alignment metric normalised per object so that its best anchor gets the object's best IoU: a
soft, quality-aware classification target instead of a hard 1.

Small objects: YOLOv8 leaves an object with no anchor centre strictly inside its box (narrower
than the finest stride: under 4 px with P2, 8 px without) without a positive, so it is never
learned. Distant cars in pole and drone views are that small, so here such an object takes the
anchor nearest to its box centre as its only candidate.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from omnigen.detector.model.boxes import box_iou


@dataclass
class Assignment:
    """Per-anchor targets of one batch; entries of background anchors are zeros."""

    target_boxes: torch.Tensor  # (B, A, 4) xyxy of the assigned object
    target_scores: torch.Tensor  # (B, A, nc) soft one-hot classification target
    target_labels: torch.Tensor  # (B, A) long class of the assigned object
    fg_mask: torch.Tensor  # (B, A) bool: the anchor is a positive
    target_gt_idx: torch.Tensor  # (B, A) long slot of the assigned object in the padded GT (M) axis


class TaskAlignedAssigner:
    """Assigns objects to anchors by the task-aligned metric; see the module docstring."""

    def __init__(self, topk: int = 10, alpha: float = 0.5, beta: float = 6.0, eps: float = 1e-9):
        if topk < 1:
            raise ValueError(f"TaskAlignedAssigner: topk must be >= 1, got {topk}")
        self.topk, self.alpha, self.beta, self.eps = topk, alpha, beta, eps

    @torch.no_grad()
    def __call__(self, pd_scores: torch.Tensor, pd_boxes: torch.Tensor, anchors: torch.Tensor,
                 gt_labels: torch.Tensor, gt_boxes: torch.Tensor, gt_mask: torch.Tensor) -> Assignment:
        """Assign a batch.

        pd_scores (B, A, nc) sigmoid scores; pd_boxes (B, A, 4) decoded xyxy; anchors (A, 2);
        gt_labels (B, M) long; gt_boxes (B, M, 4) xyxy; gt_mask (B, M) bool, False on padding.
        M may be 0 (a batch without objects).

        Works on the sparse list of (image, object, anchor) candidate triples rather than dense
        (B, M, A) tensors: an object covers few anchors, so this is several times faster and
        smaller at 640 px with the P2 level (A = 34,000) and many objects per image.
        """
        b, a, nc = pd_scores.shape
        m = gt_boxes.shape[1]
        bi, mi, ai = self._candidates(anchors, gt_boxes, gt_mask)
        if bi.numel() == 0:
            return _empty(pd_scores, pd_boxes)
        labels = gt_labels.long()[bi, mi]
        iou = box_iou(gt_boxes[bi, mi], pd_boxes[bi, ai]).clamp(min=0)
        metric = pd_scores[bi, ai, labels].pow(self.alpha) * iou.pow(self.beta)

        # The topk candidates of each object by metric (ties: lower anchor index first).
        obj = bi * m + mi
        keep = _rank_within(obj, metric, b * m) < self.topk
        # One object per anchor: the one whose box the anchor's prediction overlaps most.
        keep[keep.clone()] = _rank_within((bi * a + ai)[keep], iou[keep], b * a) == 0
        bi, mi, ai, obj, labels, iou, metric = (t[keep] for t in (bi, mi, ai, obj, labels, iou, metric))

        # Soft targets: the metric scaled per object so that its best anchor gets its best IoU.
        best_metric = _group_max(metric, obj, b * m)
        best_iou = _group_max(iou, obj, b * m)
        norm = metric * best_iou[obj] / best_metric[obj].clamp(min=self.eps)

        res = _empty(pd_scores, pd_boxes)
        res.fg_mask[bi, ai] = True
        res.target_gt_idx[bi, ai] = mi
        res.target_labels[bi, ai] = labels
        res.target_boxes[bi, ai] = gt_boxes[bi, mi].to(res.target_boxes.dtype)
        res.target_scores[bi, ai, labels] = norm.to(res.target_scores.dtype)
        return res

    def _candidates(self, anchors: torch.Tensor, gt_boxes: torch.Tensor, gt_mask: torch.Tensor):
        """(image, object, anchor) index triples of anchor centres strictly inside real objects' boxes."""
        x = anchors[:, 0].view(1, 1, -1)
        y = anchors[:, 1].view(1, 1, -1)
        x1, y1, x2, y2 = (gt_boxes[:, :, i : i + 1] for i in range(4))
        inside = (x > x1 + self.eps) & (x < x2 - self.eps) & (y > y1 + self.eps) & (y < y2 - self.eps)
        inside &= gt_mask[:, :, None]
        orphan = gt_mask & ~inside.any(-1)  # real objects too small to contain an anchor centre
        if orphan.any():
            bo, mo = orphan.nonzero(as_tuple=True)
            centre = (gt_boxes[bo, mo, :2] + gt_boxes[bo, mo, 2:]) / 2
            nearest = torch.cdist(centre.to(anchors.dtype), anchors).argmin(1)
            inside[bo, mo, nearest] = True
        return inside.nonzero(as_tuple=True)


def _rank_within(groups: torch.Tensor, values: torch.Tensor, num_groups: int) -> torch.Tensor:
    """Rank (0 = largest) of each value among those of its group; ties keep the input order."""
    by_value = torch.argsort(values, descending=True, stable=True)
    order = by_value[torch.argsort(groups[by_value], stable=True)]
    counts = torch.bincount(groups, minlength=num_groups)
    starts = torch.cumsum(counts, 0) - counts
    rank = torch.empty_like(groups)
    rank[order] = torch.arange(len(order), device=groups.device) - starts[groups[order]]
    return rank


def _group_max(values: torch.Tensor, groups: torch.Tensor, num_groups: int) -> torch.Tensor:
    out = torch.zeros(num_groups, dtype=values.dtype, device=values.device)
    return out.scatter_reduce(0, groups, values, reduce="amax", include_self=True)


def _empty(pd_scores: torch.Tensor, pd_boxes: torch.Tensor) -> Assignment:
    b, a, _ = pd_scores.shape
    long = dict(dtype=torch.long, device=pd_scores.device)
    return Assignment(target_boxes=torch.zeros_like(pd_boxes), target_scores=torch.zeros_like(pd_scores),
                      target_labels=torch.zeros(b, a, **long), fg_mask=torch.zeros(b, a, dtype=torch.bool,
                                                                                     device=pd_scores.device),
                      target_gt_idx=torch.zeros(b, a, **long))
