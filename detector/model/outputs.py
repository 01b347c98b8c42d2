"""What the detector's head hands to the loss and to inference, and how raw outputs are decoded.

This module is the seam between the model (backbone, neck, head) and everything that consumes it
(the task-aligned assigner, the loss, prediction, ONNX export). Keeping the tensor layout and the
decoding rules in one place means the loss trains exactly what inference decodes.

Layout: every per-anchor tensor is (B, C, A), anchors of all levels concatenated from the finest
stride to the coarsest, row-major within a level. Coordinates are pixels of the network input.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from omnigen.conventions import NUM_KEYPOINTS
from omnigen.detector.model.boxes import box_area
from omnigen.detector.model.heading import orient

REG_MAX = 16
"""Bins of the distribution focal loss: each box side is a distribution over 0..REG_MAX-1 strides."""

KPT_MODES = ("anchor", "box")
"""How the keypoint branch's raw x, y outputs become corners (decode_keypoints says why there are two)."""


@dataclass
class HeadOutput:
    """Raw, undecoded head outputs of one batch (training mode)."""

    box: torch.Tensor  # (B, 4 * REG_MAX, A) DFL logits for the left, top, right, bottom distances
    cls: torch.Tensor  # (B, nc, A) class logits
    kpt: torch.Tensor  # (B, NUM_KEYPOINTS * 3, A) per corner: x offset, y offset, visibility logit
    anchors: torch.Tensor  # (A, 2) anchor centres in input pixels ((i + 0.5) * stride)
    strides: torch.Tensor  # (A,) stride of each anchor's level
    kpt_mode: str = "anchor"  # KPT_MODES: how `kpt` decodes (decode_keypoints)
    heading: torch.Tensor | None = None  # (B, 3, A) direction of the image heading (heading-aware heads, heading.py)
    # a crop-stage model's forward given crops (crop_stage.py): their headings (N, 3) and corners
    # (N, 8, 2, in crop units), the rows of the flat targets they were cut for (N,) and the boxes
    # they were cut about (N, 4: the targets' boxes, moved at random)
    crop_heading: torch.Tensor | None = None
    crop_corners: torch.Tensor | None = None
    crop_logits: torch.Tensor | None = None  # (N, nc) class logits of a stage with crop_classes
    crop_rows: torch.Tensor | None = None
    crop_boxes: torch.Tensor | None = None

    @property
    def num_classes(self) -> int:
        return self.cls.shape[1]


@dataclass
class Detections:
    """Detections of one image, in the coordinates of the tensor they were decoded from: what NMS
    (prediction/nms.py) hands on and the crop stage (crop_stage.py) refines, so it lives with the
    model, below both."""

    boxes: torch.Tensor  # (n, 4) xyxy
    scores: torch.Tensor  # (n,)
    classes: torch.Tensor  # (n,) long
    keypoints: torch.Tensor  # (n, 8, 3) x, y, visibility score
    # (n, nc) every class's score at each detection's anchor (postprocess(class_scores=True)): what
    # a crop stage that names classes needs to relabel a single-label detection (crop_stage.py)
    class_scores: torch.Tensor | None = None

    def __len__(self) -> int:
        return len(self.scores)

    def take(self, index: torch.Tensor) -> "Detections":
        """The detections at `index` (indices or a boolean mask), every field alike."""
        return Detections(self.boxes[index], self.scores[index], self.classes[index], self.keypoints[index],
                          None if self.class_scores is None else self.class_scores[index])


def make_anchors(shapes: list[tuple[int, int]], strides: list[int], device=None, dtype=torch.float32
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """Anchor centres (A, 2) in input pixels and strides (A,) for feature maps of `shapes` (h, w)."""
    points, stride_list = [], []
    for (h, w), s in zip(shapes, strides):
        ys = (torch.arange(h, device=device, dtype=dtype) + 0.5) * s
        xs = (torch.arange(w, device=device, dtype=dtype) + 0.5) * s
        yy, xx = torch.meshgrid(ys, xs, indexing="ij")
        points.append(torch.stack([xx, yy], -1).reshape(-1, 2))
        stride_list.append(torch.full((h * w,), float(s), device=device, dtype=dtype))
    return torch.cat(points), torch.cat(stride_list)


def dfl_expectation(box: torch.Tensor) -> torch.Tensor:
    """(B, 4 * REG_MAX, A) logits -> (B, 4, A) expected distances in strides (softmax over bins)."""
    b, _, a = box.shape
    prob = box.view(b, 4, REG_MAX, a).softmax(2)
    bins = torch.arange(REG_MAX, device=box.device, dtype=prob.dtype).view(1, 1, REG_MAX, 1)
    return (prob * bins).sum(2)


def decode_boxes(box: torch.Tensor, anchors: torch.Tensor, strides: torch.Tensor) -> torch.Tensor:
    """DFL logits -> (B, 4, A) xyxy boxes in input pixels."""
    ltrb = dfl_expectation(box) * strides
    centre = anchors.T.unsqueeze(0)  # (1, 2, A)
    return torch.cat([centre - ltrb[:, :2], centre + ltrb[:, 2:]], 1)


def decode_keypoints(kpt: torch.Tensor, anchors: torch.Tensor, strides: torch.Tensor,
                     boxes: torch.Tensor | None = None) -> torch.Tensor:
    """Raw keypoint outputs -> (B, NUM_KEYPOINTS, 3, A): x, y in input pixels and visibility logit.

    Without `boxes` ('anchor' mode): x = anchor_x + 2 * raw_x * stride, an unbounded offset, so
    that corners of truncated objects outside the image (real targets in the record) stay
    reachable. Its targets grow with the object: a 100-pixel car seen from a stride-4 anchor needs
    raw offsets of about 6, which a freshly initialised branch (outputs near 0) reaches slowly.

    With `boxes` (B, 4, A), the anchor's decoded xyxy box ('box' mode): x = centre_x + raw_x *
    width (y with the height), the corner in units of the box around the box's centre. The raw
    targets are then the object's corner layout, about -0.7..0.7 whatever its size, and a fresh
    branch starts every corner at the box centre: the branch learns a shape, not a scale. Still
    unbounded, so out-of-image corners stay reachable. The box's size is floored at one stride so a
    degenerate early box cannot zero the corners' gradient.
    """
    b, _, a = kpt.shape
    k = kpt.view(b, NUM_KEYPOINTS, 3, a)
    if boxes is None:
        xy = anchors.T.view(1, 1, 2, a) + k[:, :, :2] * 2.0 * strides.view(1, 1, 1, a)
    else:
        centre = (boxes[:, :2] + boxes[:, 2:]) / 2  # (B, 2, A)
        size = torch.maximum(boxes[:, 2:] - boxes[:, :2], strides.view(1, 1, a))
        xy = centre.unsqueeze(1) + k[:, :, :2] * size.unsqueeze(1)
    return torch.cat([xy, k[:, :, 2:]], 2)


def head_keypoints(out: HeadOutput, boxes: torch.Tensor) -> torch.Tensor:
    """decode_keypoints in the head's own mode; `boxes` (B, 4, A) are its decoded boxes (used in
    'box' mode only: the loss passes them detached, so corners do not pull the box)."""
    return decode_keypoints(out.kpt, out.anchors, out.strides, boxes if out.kpt_mode == "box" else None)


def apply_heading(k: torch.Tensor, heading: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
    """Corners (B, K, C, A) put in the labelled order by a heading-aware head: the layout as the
    branch ordered it has an image heading (heading.image_heading, on the decoded boxes' areas);
    where it points away from the predicted heading (B, 3, A), the front is the other face."""
    turned = orient(k.permute(0, 3, 1, 2), box_area(boxes.transpose(1, 2)), heading.transpose(1, 2))
    return turned.permute(0, 2, 3, 1).contiguous()  # the layout decode's sigmoid reads (its vector path)


def decode(out: HeadOutput) -> torch.Tensor:
    """The inference tensor (B, 4 + nc + NUM_KEYPOINTS * 3, A): xyxy box, class scores (sigmoid),
    and per corner x, y, visibility score (sigmoid), corners in the labelled order (a heading-aware
    head's heading applied). NMS is applied outside (detector/prediction/nms.py)."""
    boxes = decode_boxes(out.box, out.anchors, out.strides)
    scores = out.cls.sigmoid()
    k = head_keypoints(out, boxes)
    if out.heading is not None:
        k = apply_heading(k, out.heading, boxes)
    k = torch.cat([k[:, :, :2], k[:, :, 2:].sigmoid()], 2)
    return torch.cat([boxes, scores, k.flatten(1, 2)], 1)
