"""Non-maximum suppression in plain PyTorch, outside the exported graph.

torchvision is not a dependency, so the greedy NMS is written here: class-aware by offsetting the
boxes of each class far apart, then a loop over the score-sorted candidates that suppresses all
later boxes overlapping the kept one above the IoU threshold. The loop runs once per *kept* box, on
a precomputed IoU matrix, which is fast for the few thousand candidates left after the confidence
filter.
"""

from __future__ import annotations

import numpy as np
import torch

from omnigen.conventions import NUM_KEYPOINTS
from omnigen.detector.model.boxes import box_iou_pairwise
from omnigen.detector.model.outputs import Detections


def greedy_survivors(over: torch.Tensor) -> torch.Tensor:
    """Greedy NMS's survivors (bool) from the overlap matrix of score-sorted boxes, on its device.

    Box j survives iff no surviving box before it overlaps it. Iterating that rule from "all
    survive" fixes one more box per pass at least (box j depends only on boxes before it), so it
    reaches greedy NMS's result exactly, in as many passes as the longest chain of suppressions:
    a few small kernels on a GPU instead of copying the matrix to the host and looping there.
    """
    over = over.triu(1)
    keep = torch.ones(len(over), dtype=torch.bool, device=over.device)
    for _ in range(len(over)):
        new = ~(over & keep[:, None]).any(0)
        if torch.equal(new, keep):
            break
        keep = new
    return keep


def nms(boxes: torch.Tensor, scores: torch.Tensor, iou_threshold: float) -> torch.Tensor:
    """Indices of the kept boxes, by decreasing score."""
    order = scores.argsort(descending=True)
    boxes = boxes[order]
    if boxes.is_cuda:
        return order[greedy_survivors(box_iou_pairwise(boxes, boxes) > iou_threshold)]
    over = (box_iou_pairwise(boxes, boxes) > iou_threshold).cpu().numpy()
    suppressed = np.zeros(len(order), dtype=bool)
    keep = []
    for i in range(len(order)):
        if not suppressed[i]:
            keep.append(i)
            suppressed |= over[i]
    return order[torch.tensor(keep, dtype=torch.long, device=boxes.device)]


def postprocess(pred: torch.Tensor, num_classes: int, conf: float = 0.25, iou: float = 0.7,
                max_det: int = 300, max_candidates: int = 3000, multi_label: bool = False,
                class_scores: bool = False) -> list[Detections]:
    """Decoded head output (B, 4 + nc + 24, A) -> per-image detections after NMS.

    One class per anchor (its best), as single-label detectors do; or, with `multi_label`, every
    class of an anchor whose score passes `conf`, each a detection of its own, as Ultralytics'
    validation scores a model (a van that the head rates 0.4 car and 0.3 van is then still a van
    detection, ranked among the vans by 0.3). Candidates above `conf`, the best `max_candidates`
    of them, class-aware NMS, then the top `max_det`. With `class_scores` each detection also
    carries its anchor's score for every class (Detections.class_scores).
    """
    out = []
    for p in pred.transpose(1, 2):  # (A, C)
        boxes, scores_all, kpt = p[:, :4], p[:, 4:4 + num_classes], p[:, 4 + num_classes:]
        if multi_label:
            anchor, classes = (scores_all > conf).nonzero(as_tuple=True)
            boxes, scores, kpt, all_scores = boxes[anchor], scores_all[anchor, classes], kpt[anchor], scores_all[anchor]
        else:
            scores, classes = scores_all.max(1)
            sel = scores > conf
            boxes, scores, classes, kpt, all_scores = boxes[sel], scores[sel], classes[sel], kpt[sel], scores_all[sel]
        if len(scores) > max_candidates:
            top = scores.topk(max_candidates).indices
            boxes, scores, classes, kpt, all_scores = boxes[top], scores[top], classes[top], kpt[top], all_scores[top]
        offset = classes[:, None].to(boxes.dtype) * (boxes.abs().max() * 2 + 1 if len(boxes) else 1)
        keep = nms(boxes + offset, scores, iou)[:max_det] if len(scores) else classes[:0]
        out.append(Detections(boxes[keep], scores[keep], classes[keep], kpt[keep].view(-1, NUM_KEYPOINTS, 3),
                              all_scores[keep] if class_scores else None))
    return out
