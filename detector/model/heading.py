"""Which face of a cuboid is its front, read off its eight image corners: the image heading.

A cuboid turned 180 degrees about its vertical axis projects to the same eight points with front
and rear swapped (conventions.TURN_IDX), so corners alone cannot say which face is the front; the
image can (hood against boot, lights, where the cabin sits: a small CNN on 64x64 crops tells facing
left from right at 0.85 balanced accuracy, docs/detector-training.md).

A heading-aware detector (DetectorConfig.kpt_heading) therefore splits the two questions. Its
keypoint branch learns the corner layout up to the turn (loss.turn_targets picks, per object, the
order its prediction is nearer to). A three-channel branch beside it regresses the direction of the
object's *image heading*, a property of the labelled corners alone, fixed whatever the branch
predicts (unlike a turn class's target, measured and not kept, which is the branch's own choice):

    h = ((front centre - rear centre) / sqrt(box area),  (A_front - A_rear) / (A_front + A_rear))

the first two components where the front face lies in the image relative to the rear one (left,
right, up, down), the third whether the front face is the larger, nearer one (facing the camera).
h changes sign exactly under the turn, and it is zero only for a degenerate cuboid, so its
direction is defined for every object a detector sees. Decoding computes h of the predicted
layout as it is ordered and turns the layout where h disagrees with the predicted direction
(outputs.apply_heading).
"""

from __future__ import annotations

import torch

from omnigen.conventions import FRONT_CORNERS, REAR_CORNERS, TURN_IDX

HEADING_CHANNELS = 3
# Each rear tuple is its front tuple under the turn (TURN_IDX), element by element, so the turned
# layout's sums run in the same order and h(turned) is -h(layout) to the last bit.
FRONT, REAR = FRONT_CORNERS, REAR_CORNERS
FRONT_FACE = (0, 1, 5, 4)  # the front face's quad, in order around it
REAR_FACE = (2, 3, 7, 6)


def _quad_area(xy: torch.Tensor) -> torch.Tensor:
    """|shoelace area| of quads (..., 4, 2)."""
    x, y = xy[..., 0], xy[..., 1]
    return 0.5 * (x * y.roll(-1, -1) - x.roll(-1, -1) * y).sum(-1).abs()


def image_heading(xy: torch.Tensor, area: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """(..., 3) image heading of corners xy (..., 8, 2) of objects whose 2D box area is `area` (...).

    With `mask` (..., 8) bool (labelled corners), each face's centre is the mean of its labelled
    corners and the size term counts only where both faces have all four; a face with no labelled
    corner gives a zero vector (no target). Exactly antisymmetric under TURN_IDX."""
    if mask is None:
        mask = torch.ones(xy.shape[:-1], dtype=torch.bool, device=xy.device)
    w = mask.to(xy.dtype)
    xy = torch.where(mask[..., None], xy, torch.zeros_like(xy))  # unlabelled corners may hold NaN

    def centre(idx):
        n = w[..., list(idx)].sum(-1, keepdim=True)
        return (xy[..., list(idx), :] * w[..., list(idx), None]).sum(-2) / n.clamp(min=1.0), n

    front, nf = centre(FRONT)
    rear, nr = centre(REAR)
    scale = area.clamp(min=1.0).sqrt()[..., None]
    d = torch.where((nf > 0) & (nr > 0), (front - rear) / scale, torch.zeros_like(front))
    a_front, a_rear = _quad_area(xy[..., list(FRONT_FACE), :]), _quad_area(xy[..., list(REAR_FACE), :])
    whole = mask[..., list(FRONT_FACE)].all(-1) & mask[..., list(REAR_FACE)].all(-1)
    s = torch.where(whole, (a_front - a_rear) / (a_front + a_rear).clamp(min=1e-6), torch.zeros_like(a_front))
    return torch.cat([d, s[..., None]], -1)


def heading_loss(pred: torch.Tensor, target: torch.Tensor, eps: float = 1e-3) -> torch.Tensor:
    """Mean (1 - cosine) between predicted (N, 3) and target (N, 3) headings, over the objects whose
    target is not (near) zero; 0 with a gradient when there are none."""
    norm = target.norm(dim=-1)
    keep = norm > eps
    cos = (pred * target).sum(-1) / (pred.norm(dim=-1).clamp(min=eps) * norm.clamp(min=eps))
    return ((1.0 - cos) * keep).sum() / keep.sum().clamp(min=1)


def orient(keypoints: torch.Tensor, area: torch.Tensor, heading: torch.Tensor) -> torch.Tensor:
    """Layouts (..., 8, C) turned 180 degrees (TURN_IDX, every channel with its corner) where their
    own image heading, on box areas `area` (...), points away from the predicted `heading` (..., 3):
    the one rule the head's decode (outputs.apply_heading) and the crop stage (crop_stage) share."""
    agree = (image_heading(keypoints[..., :2], area) * heading).sum(-1)
    return torch.where((agree < 0)[..., None, None], keypoints[..., list(TURN_IDX), :], keypoints)
