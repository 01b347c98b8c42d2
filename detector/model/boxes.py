"""Box arithmetic the model, the assigner and the loss share: area, IoU, CIoU and the box <->
side-distance maps.

All boxes are xyxy in pixels of the network input. Kept apart from the loss so that the assigner
(which ranks anchors by IoU) and the box loss (which trains CIoU) measure overlap the same way, and
with the model, below training, because the head's decoding and the crop stage measure boxes too.
"""

from __future__ import annotations

import math

import torch

EPS = 1e-7
"""Guards divisions by empty unions, zero heights and zero enclosing diagonals."""


def box_area(boxes: torch.Tensor) -> torch.Tensor:
    """(..., 4) xyxy -> (...) area; degenerate (inverted) boxes count as 0."""
    return (boxes[..., 2] - boxes[..., 0]).clamp(min=0) * (boxes[..., 3] - boxes[..., 1]).clamp(min=0)


def box_iou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Elementwise IoU of broadcastable (..., 4) xyxy boxes -> (...)."""
    lt = torch.maximum(a[..., :2], b[..., :2])
    rb = torch.minimum(a[..., 2:], b[..., 2:])
    inter = (rb - lt).clamp(min=0).prod(-1)
    return inter / (box_area(a) + box_area(b) - inter + EPS)


def box_iou_pairwise(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """IoU of every box of (N, 4) `a` with every box of (M, 4) `b` -> (N, M)."""
    return box_iou(a[:, None, :], b[None, :, :])


def box_ciou(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Elementwise complete IoU (Zheng et al. 2020) of (..., 4) xyxy boxes -> (...).

    CIoU = IoU - centre distance^2 / enclosing diagonal^2 - alpha * v, with v the aspect-ratio
    disagreement. Unlike plain IoU it still has a gradient when the boxes do not overlap, which is
    what a freshly initialised head needs. alpha is a weight, not a path for gradients (as in the paper).
    """
    iou = box_iou(a, b)
    w1, h1 = a[..., 2] - a[..., 0], (a[..., 3] - a[..., 1]).clamp(min=EPS)
    w2, h2 = b[..., 2] - b[..., 0], (b[..., 3] - b[..., 1]).clamp(min=EPS)
    enclose_wh = torch.maximum(a[..., 2:], b[..., 2:]) - torch.minimum(a[..., :2], b[..., :2])
    diag2 = enclose_wh.pow(2).sum(-1) + EPS
    centre2 = ((a[..., :2] + a[..., 2:]) - (b[..., :2] + b[..., 2:])).pow(2).sum(-1) / 4
    v = (4 / math.pi**2) * (torch.atan(w2 / h2) - torch.atan(w1 / h1)).pow(2)
    with torch.no_grad():
        alpha = v / (v - iou + (1 + EPS))
    return iou - (centre2 / diag2 + alpha * v)


def bbox2dist(anchors: torch.Tensor, boxes: torch.Tensor, max_dist: float) -> torch.Tensor:
    """xyxy boxes (..., 4) around anchor points (..., 2) -> left, top, right, bottom distances.

    Used for the DFL targets (call it with anchors and boxes already divided by the stride). The
    distances are clamped to [0, max_dist - 0.01] so that the upper of the two interpolated bins
    (floor + 1) still exists.
    """
    ltrb = torch.cat([anchors - boxes[..., :2], boxes[..., 2:] - anchors], -1)
    return ltrb.clamp(0, max_dist - 0.01)


def dist2bbox(distance: torch.Tensor, anchors: torch.Tensor) -> torch.Tensor:
    """Left, top, right, bottom distances (..., 4) from anchor points (..., 2) -> xyxy boxes."""
    return torch.cat([anchors - distance[..., :2], anchors + distance[..., 2:]], -1)
