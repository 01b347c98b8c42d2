"""The image's vertical vanishing point, and predicted corners turned to it.

Why. Every upright edge of a frame (a box's four vertical edges, corner i to i + 4) lies on a line
through one point: the image of the ground's downward direction. Where that point lies depends
on the camera's pitch and focal length, which the crop stage cannot see: a drone's is below the
image centre or inside the image, an upright car camera's at infinity. Edges that miss it are
what tilts a lifted box most (make validate's vertical edges
turned to the true point took its adherence from 5.84 to 4.76 deg). The detector is never given
calibration, so the point is found in the image:

- first from the detections themselves (`fit_vertical_vanishing_point`). That alone helps little:
  the crop stage's errors lean the same way across an image (it guesses the camera from where
  the crop lies), so their common point inherits the lean (7.2 deg off on 120 of make
  validate's train frames from the drone, median);
- then from the image's own straight lines (`refine_with_segments`). A city is full of upright
  edges far longer and straighter than a box's: buildings' corners, poles, window columns. The
  detections' point picks which family of line segments is the vertical one, and those segments
  place it (0.1 and 0.2 deg on the car and pole cameras' frames, 1.4 on the drone's, median).

`snap_vertical` then turns each detection's four vertical edges about their midpoints to point
at it, so that they agree with the image and with each other, as a box's do. `omnigen predict
--vertical lines` (the default) does so after the crop stage.

Coordinates are about the image's centre ((W - 1) / 2, (H - 1) / 2), in units of its longer side
(crop_stage.crop_position's). A point is a unit homogeneous 3-vector v, signed so that its image
motion v_xy - p v_z at a point p runs from an object's top face to its bottom face (a point at
infinity, an upright camera's, has v_z = 0).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

TOP, BOTTOM = slice(0, 4), slice(4, 8)  # the contract's top corners 0-3 and the ground-contact ones under them
ROBUST_SCALE = 0.05
"""IRLS's Cauchy scale, as the sine of the angle between an edge and the direction to the point:
edges off by more than about 3 degrees weigh less and less."""
MIN_BOXES = 2
"""Distinct detections needed to fit a point: one box's own four edges give its own tilt back."""


def to_normalised(xy: np.ndarray, width: float, height: float) -> np.ndarray:
    """Input pixels -> coordinates about the input's centre in units of its longer side (a point
    far away stays well conditioned): crop_stage.crop_position's frame."""
    return (np.asarray(xy, dtype=np.float64) - np.array([(width - 1) / 2, (height - 1) / 2])) / max(width, height)


def from_normalised(x: np.ndarray, width: float, height: float) -> np.ndarray:
    """The inverse of `to_normalised`: back to input pixels."""
    return np.asarray(x, dtype=np.float64) * max(width, height) + np.array([(width - 1) / 2, (height - 1) / 2])


@dataclass
class Edges:
    """Line segments from `a` to `b` (M, 2, normalised coordinates) with a length and finite ends:
    their homogeneous lines (unit normals), midpoints, unit directions and lengths."""

    lines: np.ndarray
    mid: np.ndarray
    unit: np.ndarray
    length: np.ndarray
    kept: np.ndarray  # (M_given,) bool: which of the segments given these are

    @classmethod
    def between(cls, a: np.ndarray, b: np.ndarray) -> "Edges":
        with np.errstate(invalid="ignore"):
            length = np.linalg.norm(b - a, axis=1)
            kept = (length > 1e-9) & np.isfinite(length) & np.isfinite(a + b).all(1)  # a non-finite end: no edge
        a, b, length = a[kept], b[kept], length[kept]
        ones = np.ones((len(a), 1))
        lines = np.cross(np.hstack([a, ones]), np.hstack([b, ones])) / length[:, None]
        return cls(lines, (a + b) / 2, (b - a) / length[:, None], length, kept)

    def sines(self, points: np.ndarray) -> np.ndarray:
        """(C, M) `_sines` of these edges to each point (C, 3)."""
        return _sines(points, self.mid, self.unit)

    def refit(self, weight: np.ndarray, scale: float, v: np.ndarray | None = None, iterations: int = 5
              ) -> np.ndarray:
        """The least-squares point of the lines, each weighted `weight` times a Cauchy function
        (scale `scale`, as a sine) of its miss of the previous point (IRLS; from equal weights
        where `v` is None)."""
        for _ in range(iterations):
            r = weight if v is None else weight * (1.0 / (1.0 + (self.sines(v[None])[0] / scale) ** 2))
            v = np.linalg.eigh((self.lines * r[:, None]).T @ self.lines)[1][:, 0]
        return v


def fit_vertical_vanishing_point(kp: np.ndarray, weights: np.ndarray, width: float, height: float,
                                 iterations: int = 5) -> np.ndarray:
    """The unit homogeneous point (3,), in `to_normalised` coordinates and signed as the module
    says, that the vertical edges of boxes `kp` (N, 8, 2 pixels) point at: the least-squares point
    of their lines, each weighted by its box's weight and its length (a short edge's direction is
    noise), reweighted by a Cauchy function of each edge's angular miss (IRLS), so that a few wrong
    boxes do not pull it. A point at infinity (an upright camera's vertical edges are parallel) has
    third component 0."""
    edges = vertical_edges(kp, width, height)
    if not len(edges.length):
        raise ValueError("fit_vertical_vanishing_point: no vertical edge of non-zero length")
    w = np.repeat(np.asarray(weights, dtype=np.float64), 4)[edges.kept] * edges.length
    v = edges.refit(w, ROBUST_SCALE, iterations=iterations)
    robust = 1.0 / (1.0 + (edges.sines(v[None])[0] / ROBUST_SCALE) ** 2)
    motion = v[None, :2] - edges.mid * v[2]
    if np.sum(w * robust * edges.length * np.sum(motion * edges.unit, axis=1)) < 0:
        v = -v
    return v


def vertical_edges(kp: np.ndarray, width: float, height: float) -> Edges:
    """The four vertical edges (corner i to i + 4) of each box `kp` (N, 8, 2 pixels), top to bottom,
    in `to_normalised` coordinates (`kept` indexes the 4 N edges, box by box)."""
    x = to_normalised(kp, width, height)
    return Edges.between(x[:, TOP].reshape(-1, 2), x[:, BOTTOM].reshape(-1, 2))


@dataclass(frozen=True)
class SnapOptions:
    """How `snap_vertical` finds the image's vertical vanishing point; the defaults are
    chosen on make validate's train frames (docs/detector-training.md)."""

    score_thr: float = 0.3  # detections scored at least this fit the first guess
    min_segment: float = 20.0  # line segments shorter than this (pixels) are not used
    gate_deg: float = 30.0  # segments pointing further than this from the first guess are not vertical
    candidates: int = 30  # the longest gated segments, whose pairwise crossings are the candidate points
    inlier_deg: float = 2.0  # a segment within this of a candidate supports it (softly)
    agree_deg: float = 8.0  # how far the detections' edges may disagree with a candidate before it loses weight


def line_segments(gray: np.ndarray, min_length: float) -> np.ndarray:
    """(M, 4) x1 y1 x2 y2 of the straight segments of a uint8 gray image at least `min_length`
    pixels long (OpenCV's LSD line segment detector)."""
    found = cv2.createLineSegmentDetector().detect(np.ascontiguousarray(gray))[0]
    if found is None:
        return np.zeros((0, 4))
    seg = found.reshape(-1, 4).astype(np.float64)
    return seg[np.linalg.norm(seg[:, 2:] - seg[:, :2], axis=1) >= min_length]


def _sines(points: np.ndarray, mid: np.ndarray, unit: np.ndarray) -> np.ndarray:
    """(C, S) the sine of the angle between each segment (midpoint `mid`, unit direction `unit`,
    (S, 2)) and the direction from its midpoint to each point (C, 3)."""
    to = points[:, None, :2] - mid[None] * points[:, None, 2:3]
    to = to / np.maximum(np.linalg.norm(to, axis=-1, keepdims=True), 1e-12)
    return np.abs(unit[None, :, 0] * to[..., 1] - unit[None, :, 1] * to[..., 0])


def refine_with_segments(first: np.ndarray, kp: np.ndarray, weights: np.ndarray, segments: np.ndarray,
                         width: float, height: float, opts: SnapOptions = SnapOptions()) -> np.ndarray:
    """The point (3,) of the image's vertical line segments `segments` (M, 4 pixels) nearest to
    what the boxes `kp` (N, 8, 2 pixels, weighted `weights`) say: `first`, their fitted point,
    where too few segments point near it.

    Segments pointing within gate_deg of `first` are kept. Each crossing of two of the longest
    of them is a candidate, as is `first`. A candidate's score is the length of the segments that
    point at it (each weighted 1 - (sine / sine(inlier_deg))^2 where positive). It is lowered by
    exp(-(m / sine(agree_deg))^2), m the boxes' weighted mean sine of disagreement (each edge's
    capped at 0.5, 30 deg, so that a few wild boxes do not veto a candidate). The
    disagreement matters because a city's horizontal edges (roofs, kerbs, road markings) meet at
    points of their own with as much support. The best candidate is then refit by least squares
    over the segments, reweighted by a Cauchy function of their miss (IRLS)."""
    seg = Edges.between(to_normalised(segments[:, :2], width, height), to_normalised(segments[:, 2:], width, height))
    keep = seg.sines(first[None])[0] < math.sin(math.radians(opts.gate_deg))
    if keep.sum() < 3:
        return first
    seg = Edges(seg.lines[keep], seg.mid[keep], seg.unit[keep], seg.length[keep], keep)
    longest = np.argsort(-seg.length, kind="stable")[:opts.candidates]
    i, j = np.triu_indices(len(longest), 1)
    cross = np.cross(seg.lines[longest[i]], seg.lines[longest[j]])
    norm = np.linalg.norm(cross, axis=1)
    candidates = np.vstack([first, cross[norm > 1e-12] / norm[norm > 1e-12, None]])
    inlier = math.sin(math.radians(opts.inlier_deg))
    support = (seg.length[None] * np.clip(1 - (seg.sines(candidates) / inlier) ** 2, 0, None)).sum(1)
    boxes = vertical_edges(kp, width, height)
    w = np.repeat(np.asarray(weights, dtype=np.float64), 4)[boxes.kept] * boxes.length
    if w.sum() > 0:
        disagree = (w[None] * np.minimum(boxes.sines(candidates), 0.5)).sum(1) / w.sum()
        support = support * np.exp(-(disagree / math.sin(math.radians(opts.agree_deg))) ** 2)
    v = seg.refit(seg.length, inlier, v=candidates[int(np.argmax(support))])
    return v if np.dot(v, first) >= 0 else -v


def turn_vertical_edges(kp: np.ndarray, v: np.ndarray, width: float, height: float) -> np.ndarray:
    """Boxes `kp` (N, 8, 2 pixels) with each vertical edge turned about its midpoint, its length
    and its sense kept, to lie on the line through the point `v` (`to_normalised` coordinates)."""
    kp = np.asarray(kp, dtype=np.float64)
    x = to_normalised(kp, width, height)
    top, bottom = x[:, TOP], x[:, BOTTOM]
    mid, edge = (top + bottom) / 2, bottom - top
    with np.errstate(invalid="ignore"):  # a box with a non-finite corner: left as it was below
        half = np.linalg.norm(edge, axis=-1, keepdims=True) / 2
        to_v = v[:2] - mid * v[2]
        to_v /= np.maximum(np.linalg.norm(to_v, axis=-1, keepdims=True), 1e-12)
        to_v *= np.where(np.sum(to_v * edge, axis=-1, keepdims=True) < 0, -1.0, 1.0)
        out = np.concatenate([mid - to_v * half, mid + to_v * half], axis=1)
    out = from_normalised(out, width, height)
    finite = np.isfinite(out).all(axis=(1, 2))
    return np.where(finite[:, None, None], out, kp)  # a box with a non-finite corner is left as it was


def distinct_rows(kp: np.ndarray, candidates: np.ndarray) -> np.ndarray:
    """`candidates` (indices into kp) with repeated corner sets dropped, first kept: multi-label
    prediction repeats a box and its corners once per class, and each box should count once."""
    if not len(candidates):
        return candidates
    _, first = np.unique(kp[candidates].reshape(len(candidates), -1), axis=0, return_index=True)
    return candidates[np.sort(first)]


def vertical_points(gray: np.ndarray, kp: np.ndarray, scores: np.ndarray, opts: SnapOptions = SnapOptions()
                    ) -> tuple[np.ndarray, np.ndarray] | None:
    """The vertical vanishing point of image `gray` (H, W uint8), in `to_normalised` coordinates,
    twice: fitted from the detections `kp` (N, 8, 2 pixels) scored `scores` at least
    opts.score_thr (the first guess), and refined with the image's line segments (the point);
    None where fewer than MIN_BOXES distinct detections qualify."""
    height, width = gray.shape[:2]
    use = distinct_rows(kp, np.flatnonzero(np.asarray(scores) >= opts.score_thr))
    if len(use) < MIN_BOXES:
        return None
    try:
        first = fit_vertical_vanishing_point(kp[use], scores[use], width, height)
    except ValueError:
        return None
    return first, refine_with_segments(first, kp[use], scores[use], line_segments(gray, opts.min_segment),
                                       width, height, opts)


def image_vertical_point(gray: np.ndarray, kp: np.ndarray, scores: np.ndarray,
                         opts: SnapOptions = SnapOptions()) -> np.ndarray | None:
    """`vertical_points`' refined point, or None."""
    found = vertical_points(gray, kp, scores, opts)
    return None if found is None else found[1]


def snap_vertical(gray: np.ndarray, kp: np.ndarray, scores: np.ndarray,
                  opts: SnapOptions = SnapOptions()) -> np.ndarray:
    """Detections' corners `kp` (N, 8, 2 pixels of `gray`) with their vertical edges turned to the
    image's vertical vanishing point (`image_vertical_point`); unchanged where none is found."""
    kp = np.asarray(kp, dtype=np.float64)
    v = image_vertical_point(gray, kp, np.asarray(scores, dtype=np.float64), opts)
    if v is None:
        return kp
    height, width = gray.shape[:2]
    return turn_vertical_edges(kp, v, width, height)
