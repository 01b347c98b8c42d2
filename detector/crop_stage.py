"""The front of each object read from its own image crop: a second, crop-level heading stage.

Why a second stage: the heading-aware head (heading.py) regresses an object's image heading from
the one feature vector at its anchor, shared with the box, class and corners of a nano model. On
the CPU budget that head never learns it (its 1 - cosine stays near 0.93: docs/detector-training.md),
while a small CNN on 64x64 crops of the same objects tells facing left from facing right with a
balanced accuracy of 0.85 after 400 steps (benchmarks/heading_visibility.py). The cue is in the
pixels of the object; the anchor's features do not carry it yet. So the detector crops each
object out of its own input image (bilinear, square about the box centre, as that benchmark
does) and a small CNN of that benchmark's shape regresses the image heading's direction from the
crop. The corners still come from the keypoint branch, learned up to the turn; after NMS the crop
heading decides which face of each detection's layout is the front (`heading.orient`).

Training crops the labelled boxes (the targets, in the augmented batch) and learns with the same
target and loss as the head's channels: heading.image_heading of the labelled corners, 1 - cosine.
At most MAX_CROPS objects a step, drawn at random, keep its cost a fraction of the detector's.
Inference crops the predicted boxes and averages the crop's heading with its mirror image's (a
horizontal flip negates the heading's x component and keeps the rest).
"""

from __future__ import annotations

from dataclasses import replace

import torch
import torch.nn as nn
import torch.nn.functional as F
import torch.onnx.operators

from omnigen.detector.boxes import box_area
from omnigen.detector.heading import HEADING_CHANNELS, image_heading, orient
from omnigen.detector.nms import Detections

MARGIN = 0.1
"""Context around the box on each side, as a share of its longer side (heading_visibility's)."""
MAX_CROPS = 128
"""Objects cropped per training step, at most (a random subset of the batch's labelled ones)."""
MAX_ORIENT = 300
"""Detections oriented per image at prediction, the best-scoring first (NMS sorts them): each costs
two passes of the crop net (the crop and its mirror), and evaluation keeps up to 1000 an image.
Those past the 300th keep the keypoint branch's own order (the heading head's, with kpt_heading).
Not fewer: a weakly trained model ranks many of its matched objects low (the learning benchmark's
400-step model: corner error 0.445 orienting 300 an image, 0.460 orienting 100; 18 labelled objects
a frame on average, 104 at most)."""
MIN_SIDE = 4.0
"""Boxes whose longer side is under this many pixels are not cropped in training: nothing to see."""
_MIRROR = (-1.0, 1.0, 1.0)  # the image heading of the horizontally mirrored crop, component by component


class HeadingNet(nn.Module):
    """Crops (N, 3, S, S) in 0..1 -> image heading directions (N, 3), unnormalised.

    Four blocks of two 3x3 convolutions, batch norm, SiLU and a 2x2 max-pool, then a global average:
    the classifier that benchmarks/heading_visibility.py showed can see the front at 64x64."""

    def __init__(self, width: int = 16):
        super().__init__()

        def block(cin: int, cout: int) -> nn.Sequential:
            return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.SiLU(),
                                 nn.Conv2d(cout, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.SiLU(),
                                 nn.MaxPool2d(2))

        self.features = nn.Sequential(block(3, width), block(width, 2 * width), block(2 * width, 4 * width),
                                      block(4 * width, 4 * width), nn.AdaptiveAvgPool2d(1), nn.Flatten())
        self.out = nn.Linear(4 * width, HEADING_CHANNELS)

    def forward(self, crops: torch.Tensor) -> torch.Tensor:
        return self.out(self.features(crops))


def crop_boxes(images: torch.Tensor, batch_index: torch.Tensor, boxes: torch.Tensor, size: int,
               margin: float = MARGIN) -> torch.Tensor:
    """Square crops (N, C, size, size) of `images` (B, C, H, W): box n (xyxy pixels) of image
    batch_index[n], grown by `margin` of its longer side on each side and squared about its centre;
    zero outside the image. Bilinear sampling (F.grid_sample), so it runs on any device and in
    ONNX. The contract's pixel convention: pixel centres at integers, an image of width W spans
    -0.5 .. W - 0.5 (detector/data.py Letterbox)."""
    # the size as a tensor, so that an ONNX graph traced at one size crops right at any other
    hw = torch.onnx.operators.shape_as_tensor(images)[2:].to(images.dtype)
    boxes = boxes.to(images.dtype)
    centre = (boxes[:, :2] + boxes[:, 2:]) / 2 + 0.5  # from the contract's pixel centres to edge-based
    half = (boxes[:, 2:] - boxes[:, :2]).amax(1).clamp(min=1.0) * (0.5 + margin)
    # grid_sample's normalised coordinates (align_corners=False): -1 and +1 are the image's outer
    # edges; the crop's pixel centres sit at (i + 0.5) / size of the square. Written out rather than
    # F.affine_grid, which ONNX has only from opset 20.
    base = (torch.arange(size, dtype=images.dtype, device=images.device) + 0.5) / size * 2 - 1  # (S,)
    gx = (centre[:, 0, None] + half[:, None] * base) * (2 / hw[1]) - 1  # (N, S)
    gy = (centre[:, 1, None] + half[:, None] * base) * (2 / hw[0]) - 1
    grid = torch.stack([gx[:, None, :].expand(-1, size, -1), gy[:, :, None].expand(-1, -1, size)], -1)
    c = images.shape[1]

    def sample(image: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        # one image's crops stacked as one tall grid: no copy of the image per crop (a thousand
        # detections of a 640x640 batch would be gigabytes)
        k = g.shape[0]
        out = F.grid_sample(image[None], g.reshape(1, k * size, size, 2), mode="bilinear", padding_mode="zeros",
                            align_corners=False)
        return out.view(c, k, size, size).transpose(0, 1)

    if images.shape[0] == 1:  # prediction's and ONNX's case (a constant while traced)
        return sample(images[0], grid)
    crops = images.new_zeros((boxes.shape[0], c, size, size))
    for b in range(images.shape[0]):
        sel = (batch_index == b).nonzero(as_tuple=True)[0]
        if len(sel):
            crops[sel] = sample(images[b], grid[sel])
    return crops


def training_rois(targets: dict[str, torch.Tensor], max_crops: int = MAX_CROPS, min_side: float = MIN_SIDE
                  ) -> torch.Tensor:
    """Rows of the flat targets to crop this step: labelled objects whose image heading is defined
    and whose box is at least min_side, at most max_crops of them drawn at random (torch's generator,
    which the trainer seeds)."""
    boxes = targets["bboxes"].float()
    side = (boxes[:, 2:] - boxes[:, :2]).amax(1) if len(boxes) else boxes.new_zeros(0)
    h = image_heading(targets["keypoints"].float(), box_area(boxes), targets["kpt_mask"].bool())
    rows = ((h.norm(dim=-1) > 1e-3) & (side >= min_side)).nonzero(as_tuple=True)[0]
    if len(rows) > max_crops:
        rows = rows[torch.randperm(len(rows), device=rows.device)[:max_crops]]
    return rows


def crop_heading(net: HeadingNet, images: torch.Tensor, batch_index: torch.Tensor, boxes: torch.Tensor,
                 size: int, mirror: bool = False) -> torch.Tensor:
    """(N, 3) headings of the boxes' crops; with `mirror`, averaged with the mirrored crop's."""
    crops = crop_boxes(images, batch_index, boxes, size)
    h = net(crops)
    if mirror:
        h = (h + net(crops.flip(-1)) * h.new_tensor(_MIRROR)) / 2
    return h


def crop_heading_chunked(net: HeadingNet, images: torch.Tensor, batch_index: torch.Tensor, boxes: torch.Tensor,
                         size: int, mirror: bool = True, chunk: int = 128) -> torch.Tensor:
    """crop_heading over at most `chunk` boxes at a time (inference: bounded memory whatever the
    number of detections)."""
    parts = [crop_heading(net, images, batch_index[i:i + chunk], boxes[i:i + chunk], size, mirror)
             for i in range(0, boxes.shape[0], chunk)]
    return torch.cat(parts) if parts else boxes.new_zeros((0, HEADING_CHANNELS))


def orient_detections(net: HeadingNet, size: int, images: torch.Tensor, dets: list[Detections],
                      max_orient: int = MAX_ORIENT) -> list[Detections]:
    """Per-image detections (in `images`' coordinates, best score first) with the layouts of the
    first `max_orient` turned to the front their crops show (mirror-averaged): what prediction does
    after NMS for a crop-heading model."""
    n = [min(len(d), max_orient) for d in dets]
    if not sum(n):
        return dets
    batch_index = torch.cat([torch.full((k,), i, dtype=torch.long, device=images.device) for i, k in enumerate(n)])
    boxes = torch.cat([d.boxes[:k] for d, k in zip(dets, n)]).to(images.dtype)
    h = crop_heading_chunked(net, images, batch_index, boxes, size)
    kpts = orient(torch.cat([d.keypoints[:k] for d, k in zip(dets, n)]), box_area(boxes), h.to(boxes.dtype)).split(n)
    return [replace(d, keypoints=torch.cat([k.to(d.keypoints.dtype), d.keypoints[len(k):]]))
            for d, k in zip(dets, kpts)]


class OrientWrapper(nn.Module):
    """The crop stage as a graph of its own for ONNX (detector/export_onnx.py), run after NMS:
    (images (1, 3, H, W) as the detector saw them, boxes (N, 4), keypoints (N, 8, 3) of the
    detections) -> the keypoints with each layout's front set by its crop (orient_detections)."""

    def __init__(self, net: HeadingNet, size: int):
        super().__init__()
        self.net, self.size = net, size

    def forward(self, images: torch.Tensor, boxes: torch.Tensor, keypoints: torch.Tensor) -> torch.Tensor:
        batch_index = torch.zeros_like(boxes[:, 0], dtype=torch.long)
        h = crop_heading(self.net, images, batch_index, boxes, self.size, mirror=True)
        return orient(keypoints, box_area(boxes), h.to(boxes.dtype))
