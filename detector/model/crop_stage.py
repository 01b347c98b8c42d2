"""Each object's corners and front read from its own image crop: a second, crop-level stage.

Why a second stage. The keypoint branch regresses an object's eight corners from the one feature
vector at its anchor, at every scale at once, shared with the box and class of a nano model. On
a CPU budget its corners stay far from the truth and its front is a coin toss (the ablations in
docs/detector-training.md). Human-pose estimation knows the alternative: top-down, a network that
sees one object at one scale; a small CNN on 64x64 crops of the same objects places their corners
much closer and tells facing left from facing right. So the detector
crops each object out of its own input image (bilinear, square about the box centre) and a small
CNN of those benchmarks' shape regresses from the crop both the corners (in the crop's units:
(x - box centre) / half side) and the image heading's direction. The keypoint branch still learns
(its corners are what the detections past MAX_REFINE keep); after NMS each of the best detections
takes the crop's corners, turned where the crop's heading says the other face is the front
(`heading.orient`).

Training crops the labelled boxes of the augmented batch, each moved at random as a detector's
boxes miss the truth (`jitter_boxes`), and learns the corners with an L1 term (`crop_corners`) and
the heading with the head's target and loss (heading.image_heading of the labelled corners,
1 - cosine; `heading_crop`). At most MAX_CROPS objects a step, drawn at random, keep its cost
bounded (benchmarks/bench_crop_stage.py prints it); a stage that names classes draws them
class-balanced (`draw_rows`). Inference crops the predicted boxes and
averages each crop's outputs with its mirror image's (a horizontal flip negates x and renumbers
the corners by FLIP_IDX; it negates the heading's x component and keeps the rest).

With classes (DetectorConfig.crop_classes) the stage also names each crop's class, and prediction
rescores each refined detection by it. Why: the head finds the vehicles and then calls most vans,
trucks and buses cars (docs/detector-training.md: `crop_stage.classes`), deciding between
look-alike classes from one anchor's feature at a stride of 4-32 pixels, where the crop net sees the object alone at 64 x 64.
Training adds a cross-entropy of the crops' class logits against the labelled classes
(`crop_cls`); prediction gives a detection of class c with score s the score sqrt(s * p_c), p the
crop's softmax (mirror-averaged logits): the geometric mean keeps the head's evidence that there
is an object there and lets the crop move the classes against each other (`rescore`). A
single-label prediction (omnigen predict) keeps each anchor's every class score through NMS
(postprocess(class_scores=True)), floored at conf^2, the least a rescored score above conf needs;
each refined detection then takes the class whose rescored score is best, so the crop can change
a box's class too, and the caller drops what falls under conf (predict.infer_batch). Detections
past MAX_REFINE keep the head's scores, on the head's scale. Two other rescorings were compared
and not kept (docs/detector-training.md): by the anchor's best score of any class (the head
finds, the crop names), and that with a detection of every class for each refined box.

Trained apart. `omnigen train-crop` (detector/training/crop_train.py) trains the stage again after the
detector, alone on clean crops of the labelled objects, and writes the detector's checkpoint with
the new stage. There the classes come from a net of their own (SplitCropNet,
DetectorConfig.crop_split): in one small net the class term costs the corners
(corner rel 0.191 alone against 0.211 with classes).

Where the crop was cut (DetectorConfig.crop_position, `train-crop --position`). A crop alone does
not say where in the image it lay, and the direction of an object's vertical edges depends on
it: they meet at the vertical vanishing point, far outside the crop (below a drone's image centre,
above it for a camera looking up). That direction is what tilts a lifted box most
(docs/detector-training.md). So the corners' net can be given each crop's `crop_position`
(the box centre about the input's centre and the log of the crop's side, in units of the input's
longer side), appended to its flattened features before the hidden layer. A mirrored crop is
told the mirrored position (`mirror_position`).
"""

from __future__ import annotations

from dataclasses import replace

import torch
import torch.nn as nn
import torch.nn.functional as F
import torch.onnx.operators

from omnigen.conventions import FLIP_IDX, NUM_KEYPOINTS
from omnigen.detector.model.boxes import box_area
from omnigen.detector.model.heading import HEADING_CHANNELS, image_heading, orient
from omnigen.detector.model.outputs import Detections

MARGIN = 0.1
"""Context around the box on each side, as a share of its longer side (that of the crops a small CNN told the front from)."""
MAX_CROPS = 128
"""Objects cropped per training step, at most (a random subset of the batch's labelled ones)."""
MAX_REFINE = 300
"""Detections refined per image at prediction, the best-scoring first (NMS sorts them): each costs
two passes of the crop net (the crop and its mirror), and evaluation keeps up to 1000 an image.
Those past the 300th keep the keypoint branch's corners (in the heading head's order, with
kpt_heading). Not fewer: a weakly trained model ranks many of its matched objects low (the
learning benchmark's 400-step model of the heading-only stage: corner error 0.445 orienting 300 an
image, 0.460 orienting 100 when rescored with this constant edited; 18 labelled objects a frame on
average, 104 at most)."""
MIN_SIDE = 4.0
"""Boxes whose longer side is under this many pixels are not cropped in training: nothing to see."""
CENTRE_JITTER = 0.06
"""Training boxes' centres move by N(0, this) of their width and height (about what a detector's
boxes miss the truth by), so that the stage places corners about predicted boxes, not only about
perfect ones."""
SIDE_JITTER = 0.1
"""...and each side is scaled by a log-normal factor of this sigma."""
HIDDEN = 128
POSITION_CHANNELS = 3
"""Where a crop was cut (`crop_position`): the box centre's x and y about the input's centre and
the log of its crop side, each in units of the input's longer side."""
MIRROR_HEADING = (-1.0, 1.0, 1.0)
"""The image heading of the horizontally mirrored crop, component by component (x negated)."""


class MaxPool2(nn.Module):
    """2 x 2 max pooling at stride 2 of even-sized maps (nn.MaxPool2d(2), which it replaces without
    a tensor of its own). In eval mode it takes the maximum of column pairs, then of row pairs: the
    same values, exactly, 2.6 to 4.4 times faster than PyTorch's CPU max_pool2d kernel on the crop
    net's maps. In training it is max_pool2d itself: amax's
    gradient splits ties (flat image regions) evenly where max_pool2d gives it to one element, and
    training stays what it was."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.training:
            return F.max_pool2d(x, 2)
        x = x.unflatten(3, (x.shape[3] // 2, 2)).amax(4)
        return x.unflatten(2, (x.shape[2] // 2, 2)).amax(3)


class CropNet(nn.Module):
    """Crops (N, 3, S, S) in 0..1 -> (N, 3 + 16 + num_classes): the image heading's direction
    (unnormalised), the eight corners (x, y) in the crop's units (`to_crop_units`) and, where
    num_classes > 0, the class logits.

    Four blocks of two 3x3 convolutions, batch norm, SiLU and a 2x2 max-pool (the shape of the
    classifier that told a vehicle's front at 64x64), then the last feature map flattened, not
    averaged: where a corner lies is what a global average would throw away. With `position`,
    each crop's `crop_position` is appended to those features (forward's `where`)."""

    def __init__(self, size: int, width: int = 16, num_classes: int = 0, position: bool = False):
        super().__init__()
        if num_classes < 0:
            raise ValueError(f"CropNet: num_classes must be >= 0, got {num_classes}")
        self.num_classes = num_classes
        self.position = position
        if size <= 0 or size % 16:
            raise ValueError(f"CropNet: crop side must be a positive multiple of 16, got {size}")

        def block(cin: int, cout: int) -> nn.Sequential:
            return nn.Sequential(nn.Conv2d(cin, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.SiLU(),
                                 nn.Conv2d(cout, cout, 3, padding=1, bias=False), nn.BatchNorm2d(cout), nn.SiLU(),
                                 MaxPool2())

        self.features = nn.Sequential(block(3, width), block(width, 2 * width), block(2 * width, 4 * width),
                                      block(4 * width, 4 * width), nn.Flatten())
        extra = POSITION_CHANNELS if position else 0
        self.hidden = nn.Sequential(nn.Linear(4 * width * (size // 16) ** 2 + extra, HIDDEN), nn.SiLU())
        self.out = nn.Linear(HIDDEN, HEADING_CHANNELS + 2 * NUM_KEYPOINTS + num_classes)

    def forward(self, crops: torch.Tensor, where: torch.Tensor | None = None) -> torch.Tensor:
        """`where` (N, POSITION_CHANNELS), `crop_position` of each crop: needed by a net built with
        `position`, ignored by one without."""
        f = self.features(crops)
        if self.position:
            if where is None:
                raise ValueError("CropNet: built with position, so each crop's crop_position is needed")
            f = torch.cat([f, where.to(f.dtype)], 1)
        return self.out(self.hidden(f))


class SplitCropNet(nn.Module):
    """CropNet's outputs from two CropNets of their own: the heading and corners from `corners`
    (no classes), the class logits from `classes` (its heading and corner outputs unused). Why:
    in one small net the class term costs the corners. Trained apart on the same crops for 2000
    steps, a net of corners alone placed them 0.191 of sqrt(box area) from the truth with the turn
    forgiven, one that also named the classes 0.211 (docs/detector-training.md). Twice the crop
    net's cost (benchmarks/bench_crop_stage.py)."""

    def __init__(self, size: int, num_classes: int, width: int = 16, position: bool = False):
        super().__init__()
        if num_classes < 1:
            raise ValueError(f"SplitCropNet: names classes, so num_classes must be >= 1, got {num_classes}")
        self.num_classes = num_classes
        # only the corners' net is told the position: where the crop was cut says nothing of its class
        self.corners = CropNet(size, width, position=position)
        self.classes = CropNet(size, width, num_classes)

    @property
    def position(self) -> bool:
        return self.corners.position

    def forward(self, crops: torch.Tensor, where: torch.Tensor | None = None) -> torch.Tensor:
        end = HEADING_CHANNELS + 2 * NUM_KEYPOINTS
        return torch.cat([self.corners(crops, where), self.classes(crops)[:, end:]], 1)


def split_outputs(y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """CropNet's (N, 19 + nc) -> headings (N, 3), corners (N, 8, 2) in crop units, class logits
    (N, nc; None without classes)."""
    end = HEADING_CHANNELS + 2 * NUM_KEYPOINTS
    logits = y[:, end:] if y.shape[1] > end else None
    return y[:, :HEADING_CHANNELS], y[:, HEADING_CHANNELS:end].reshape(-1, NUM_KEYPOINTS, 2), logits


def half_side(boxes: torch.Tensor, margin: float = MARGIN) -> torch.Tensor:
    """(N,) half the side of each box's square crop, as crop_boxes cuts it."""
    return (boxes[:, 2:] - boxes[:, :2]).amax(1).clamp(min=1.0) * (0.5 + margin)


def to_crop_units(points: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
    """Image points (N, K, 2) -> (point - box centre) / crop half side: the crop's edges at +-1."""
    centre = (boxes[:, :2] + boxes[:, 2:]) / 2
    return (points - centre[:, None]) / half_side(boxes)[:, None, None]


def from_crop_units(t: torch.Tensor, boxes: torch.Tensor) -> torch.Tensor:
    """The inverse of to_crop_units."""
    centre = (boxes[:, :2] + boxes[:, 2:]) / 2
    return t * half_side(boxes)[:, None, None] + centre[:, None]


def crop_position(boxes: torch.Tensor, hw: torch.Tensor) -> torch.Tensor:
    """(N, POSITION_CHANNELS) where each box's crop was cut from an input of size `hw` (H, W; a
    tensor, so that an ONNX graph traced at one size is right at another): the box centre's x and
    y about the input's centre, (x - (W - 1) / 2) / S, and the log of its crop side / S, S the
    input's longer side. Why: a crop alone does not say where in the image it was, and the
    direction its vertical edges point in does (they meet at a vanishing point far outside the
    crop). Mirroring the input negates the first channel."""
    hw = hw.to(boxes.dtype)
    s = hw.max()
    centre = (boxes[:, :2] + boxes[:, 2:]) / 2
    xy = (centre - (hw.flip(0) - 1) / 2) / s
    return torch.cat([xy, (half_side(boxes) * 2 / s).log()[:, None]], 1)


def mirror_position(where: torch.Tensor) -> torch.Tensor:
    """crop_position of the horizontally mirrored input's crop: x negated."""
    return where * where.new_tensor([-1.0, 1.0, 1.0])


def mirror_corners(t: torch.Tensor) -> torch.Tensor:
    """Corners (N, 8, 2) in crop units of the horizontally mirrored crop: x negated, corners renumbered."""
    return t[:, list(FLIP_IDX)] * t.new_tensor([-1.0, 1.0])


def jitter_boxes(boxes: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
    """Boxes (N, 4) moved and resized at random (CENTRE_JITTER, SIDE_JITTER), drawn from `generator`
    (default: torch's, which the detector's trainer seeds)."""
    wh = boxes[:, 2:] - boxes[:, :2]

    def normal() -> torch.Tensor:
        return torch.randn(wh.shape, generator=generator, dtype=wh.dtype, device=wh.device)

    centre = (boxes[:, :2] + boxes[:, 2:]) / 2 + normal() * CENTRE_JITTER * wh
    wh = wh * torch.exp(normal() * SIDE_JITTER)
    return torch.cat([centre - wh / 2, centre + wh / 2], 1)


def crop_boxes(images: torch.Tensor, batch_index: torch.Tensor, boxes: torch.Tensor, size: int,
               margin: float = MARGIN) -> torch.Tensor:
    """Square crops (N, C, size, size) of `images` (B, C, H, W): box n (xyxy pixels) of image
    batch_index[n], grown by `margin` of its longer side on each side and squared about its centre;
    zero outside the image. Bilinear sampling (F.grid_sample), so it runs on any device and in
    ONNX. The contract's pixel convention: pixel centres at integers, an image of width W spans
    -0.5 .. W - 0.5 (detector/data/samples.py Letterbox)."""
    # the size as a tensor, so that an ONNX graph traced at one size crops right at any other
    hw = torch.onnx.operators.shape_as_tensor(images)[2:].to(images.dtype)
    boxes = boxes.to(images.dtype)
    centre = (boxes[:, :2] + boxes[:, 2:]) / 2 + 0.5  # from the contract's pixel centres to edge-based
    half = half_side(boxes, margin)
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


def draw_rows(rows: torch.Tensor, max_crops: int, classes: torch.Tensor | None = None) -> torch.Tensor:
    """At most max_crops of the candidate `rows`, drawn at random without replacement (torch's
    generator, which the trainer seeds). Given the candidates' `classes` (len(rows),), class-balanced:
    each row drawn with weight 1 / (candidates of its class), so that every class in the batch gets
    about an equal share of the crops until its objects run out; a batch's rare objects are then
    nearly always cropped and its cars subsampled."""
    if len(rows) <= max_crops:
        return rows
    if classes is None:
        return rows[torch.randperm(len(rows), device=rows.device)[:max_crops]]
    _, inverse, counts = torch.unique(classes, return_inverse=True, return_counts=True)
    return rows[torch.multinomial(1.0 / counts[inverse].float(), max_crops, replacement=False)]


def training_rois(targets: dict[str, torch.Tensor], max_crops: int = MAX_CROPS, min_side: float = MIN_SIDE,
                  balanced: bool = False) -> torch.Tensor:
    """Rows of the flat targets to crop this step: labelled objects whose image heading is defined
    and whose box is at least min_side, at most max_crops of them (`draw_rows`, class-balanced by
    targets["cls"] where `balanced`: a stage that names classes)."""
    boxes = targets["bboxes"].float()
    side = (boxes[:, 2:] - boxes[:, :2]).amax(1) if len(boxes) else boxes.new_zeros(0)
    h = image_heading(targets["keypoints"].float(), box_area(boxes), targets["kpt_mask"].bool())
    rows = ((h.norm(dim=-1) > 1e-3) & (side >= min_side)).nonzero(as_tuple=True)[0]
    return draw_rows(rows, max_crops, targets["cls"].reshape(-1)[rows] if balanced else None)


def crop_outputs(net: CropNet, images: torch.Tensor, batch_index: torch.Tensor, boxes: torch.Tensor,
                 size: int, mirror: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Headings (N, 3), corners (N, 8, 2, crop units) and class logits (N, nc, or None) of the
    boxes' crops; with `mirror`, each averaged with the mirrored crop's (a class is the same
    mirrored). A net built with `position` is told where each crop was cut (`crop_position`)."""
    where = crop_position(boxes, torch.onnx.operators.shape_as_tensor(images)[2:]) if reads_position(net) else None
    return outputs_of_crops(net, crop_boxes(images, batch_index, boxes, size), mirror, where)


def reads_position(net: nn.Module) -> bool:
    """Whether `net` was built to be told where its crops were cut (CropNet's `position`)."""
    return bool(getattr(net, "position", False))


def outputs_of_crops(net: CropNet, crops: torch.Tensor, mirror: bool = False, where: torch.Tensor | None = None
                     ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """crop_outputs of crops already cut (N, 3, S, S in 0..1) and their `crop_position` (`where`,
    read only by a net built with `position`): a caller scores a trained stage on
    its own crops so."""
    if not reads_position(net):
        where = None
    h, t, c = split_outputs(net(crops, where))
    if mirror:
        hm, tm, cm = split_outputs(net(crops.flip(-1), None if where is None else mirror_position(where)))
        h = (h + hm * h.new_tensor(MIRROR_HEADING)) / 2
        t = (t + mirror_corners(tm)) / 2
        c = None if c is None else (c + cm) / 2
    return h, t, c


def refine(net: CropNet, size: int, images: torch.Tensor, batch_index: torch.Tensor, boxes: torch.Tensor,
           keypoints: torch.Tensor, chunk: int = 128) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Keypoints (N, 8, C) of detections `boxes` (N, 4) of `images`: x, y replaced by their crops'
    corners (mirror-averaged), the layout turned where the crop's heading says the other face is the
    front; the other channels (visibility) kept. With them the crops' class probabilities (N, nc;
    None for a net without classes). At most `chunk` crops at a time: bounded memory whatever the
    number of detections."""
    parts = [crop_outputs(net, images, batch_index[i:i + chunk], boxes[i:i + chunk], size, mirror=True)
             for i in range(0, boxes.shape[0], chunk)]
    probs = None
    if net.num_classes:
        probs = (torch.cat([p[2] for p in parts]) if parts else boxes.new_zeros((0, net.num_classes))
                 ).float().softmax(-1).to(boxes.dtype)
    if not parts:
        return keypoints, probs
    h = torch.cat([p[0] for p in parts]).to(boxes.dtype)
    xy = from_crop_units(torch.cat([p[1] for p in parts]).to(boxes.dtype), boxes)
    kpts = torch.cat([xy.to(keypoints.dtype), keypoints[..., 2:]], -1)
    return orient(kpts, box_area(boxes), h), probs


def rescore(scores: torch.Tensor, classes: torch.Tensor, probs: torch.Tensor) -> torch.Tensor:
    """Scores (n,) of detections of `classes` (n,) with the crop's class probabilities (n, nc):
    sqrt(score * p[class]), the geometric mean of the head's score and the crop's belief in the
    detection's class (see the module docstring)."""
    p = probs.gather(1, classes.long()[:, None])[:, 0].to(scores.dtype)
    return (scores * p).clamp(min=0).sqrt()


def distinct_boxes(boxes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(first, rank) of detections (n, 4) in score order: `first` the index of each distinct box's
    first detection, in order of it; `rank` (n,) which of them each detection's box is.

    Multi-label prediction (nms.postprocess) makes one detection per class an anchor rates above
    the floor: copies with one box and one set of corners, differing in class and score."""
    if not len(boxes):
        empty = torch.zeros(0, dtype=torch.long, device=boxes.device)
        return empty, empty
    _, inverse = torch.unique(boxes, dim=0, return_inverse=True)
    n = len(boxes)
    first = torch.full((int(inverse.max()) + 1,), n, dtype=torch.long, device=boxes.device).scatter_reduce(
        0, inverse, torch.arange(n, device=boxes.device), "amin")
    order = first.argsort()
    rank = torch.empty_like(order)
    rank[order] = torch.arange(len(order), device=boxes.device)
    return first[order], rank[inverse]


def refine_detections(net: CropNet, size: int, images: torch.Tensor, dets: list[Detections],
                      max_refine: int = MAX_REFINE, rescore_classes: bool = True) -> list[Detections]:
    """Per-image detections (in `images`' coordinates, best score first) with the corners of the
    first `max_refine` distinct boxes placed by their crops (`refine`): what prediction does after
    NMS for a crop-stage model. A box that multi-label prediction gave several classes is cropped
    once and all its detections take its corners; it takes one of the `max_refine` places, so the
    class copies do not push other objects out of the crop stage. With a net that names classes
    (and `rescore_classes`), each refined detection's score is rescored by its crop (`rescore`) and
    the detections sorted again, best first; a single-label detection that carries its anchor's
    every class score (Detections.class_scores) takes the class whose rescored score is best."""
    picked = [distinct_boxes(d.boxes) for d in dets]
    n = [min(len(first), max_refine) for first, _ in picked]
    if not sum(n):
        return dets
    chosen = [first[:k] for (first, _), k in zip(picked, n)]
    batch_index = torch.cat([torch.full((k,), i, dtype=torch.long, device=images.device) for i, k in enumerate(n)])
    boxes = torch.cat([d.boxes[c] for d, c in zip(dets, chosen)]).to(images.dtype)
    kpts, probs = refine(net, size, images, batch_index, boxes,
                         torch.cat([d.keypoints[c] for d, c in zip(dets, chosen)]))
    kpts = kpts.split(n)
    probs = probs.split(n) if probs is not None and rescore_classes else [None] * len(dets)
    out = []
    for d, (_, rank), k, p in zip(dets, picked, kpts, probs):
        refined = rank < len(k)
        keypoints = d.keypoints.clone()
        keypoints[refined] = k.to(d.keypoints.dtype)[rank[refined]]
        d = replace(d, keypoints=keypoints)
        if p is not None and refined.any():
            if d.class_scores is not None:  # single-label: each detection takes its best class, rescored
                head = d.class_scores[refined]
                best = (head * p[rank[refined]].to(head.dtype)).clamp(min=0).sqrt().max(1)
                scores, classes = d.scores.clone(), d.classes.clone()
                scores[refined], classes[refined] = best.values.to(scores.dtype), best.indices.to(classes.dtype)
                d = replace(d, scores=scores, classes=classes)
            else:  # each detection by its own class's head score
                scores = d.scores.clone()
                scores[refined] = rescore(d.scores[refined], d.classes[refined], p[rank[refined]])
                d = replace(d, scores=scores)
            d = d.take(d.scores.argsort(descending=True, stable=True))
        out.append(d)
    return out


class RefineWrapper(nn.Module):
    """The crop stage as a graph of its own for ONNX (detector/prediction/export_onnx.py), run after NMS:
    (images (1, 3, H, W) as the detector saw them, boxes (N, 4), keypoints (N, 8, 3) of the
    detections) -> the keypoints with each detection's corners and front from its crop (`refine`),
    and for a net that names classes their probabilities (N, nc) too, which a caller rescores its
    detections by (`rescore`)."""

    def __init__(self, net: CropNet, size: int):
        super().__init__()
        self.net, self.size = net, size

    def forward(self, images: torch.Tensor, boxes: torch.Tensor, keypoints: torch.Tensor
                ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        batch_index = torch.zeros_like(boxes[:, 0], dtype=torch.long)
        kpts, probs = refine(self.net, self.size, images, batch_index, boxes, keypoints, chunk=1 << 30)
        return kpts if probs is None else (kpts, probs)
