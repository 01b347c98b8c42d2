"""The calibration-free BEV head: a homography from the image to the ground plane, from footprints alone.

Why it works without intrinsics: the ground-contact corners 4-7 of every detection are the corners
of a rectangle on one plane (the ground). A homography that makes all of them rectangles again is
a metric rectification of the ground plane, and a metric rectification is unique up to a
similarity (HZ, "Multiple View Geometry", 2.7). So the head needs no K and no ground plane; those
enter only at evaluation.

Parameterisation (4 numbers, not 8). The rectifying map is written as

    H = S . A(alpha, beta) . P(l) . T

- T: Hartley normalisation of the frame's footprint points (centroid at 0, mean distance sqrt 2),
  so the numbers below are of order one whatever the image size.
- P(l) = [[1, 0, 0], [0, 1, 0], [l1, l2, 1]]: moves the vanishing line l = (l1, l2, 1) of the
  ground to infinity (affine rectification). Its third output coordinate w = l . x is proportional
  to 1 / depth, so w > 0 for every ground point in front of the camera.
- A = [[1/beta, -alpha/beta], [0, 1]]: HZ's affine-to-metric step; (alpha -/+ i beta, 1, 0) are the
  imaged circular points after P. beta is optimised as log(beta) so it stays positive.
- S: a similarity (scale, rotation, reflection, translation) that the rectangle constraints cannot
  see. It is fixed afterwards by conventions, not optimised: see `_canonical_frame`.

Loss: L_rect = sum over instances and corners of cos^2 of the angle between consecutive edges of
the warped footprint (scipy.optimize.least_squares, 'trf'), with guards:
- collapse: cosines are scale-free, log(beta) keeps the affine part invertible, and a hinge on
  each footprint's area relative to the frame's median (below AREA_FLOOR) keeps any footprint
  from being squashed to a point while others stay large;
- folding: every footprint point must stay on the camera's side of the vanishing line, w > 0.
  A hinge on w_i / max(w) below FOLD_MARGIN keeps the optimiser there, an initial vanishing line
  that cuts through footprints is pulled back towards infinity before the first step, and a
  solution that still folds is refused in favour of the other start.

The cosines go through a soft-L1 loss (scale ROBUST_COS, about 3 degrees), so a footprint with one
wrong corner is down-weighted rather than bending every other footprint. Two starts are solved, the
DLT one and the affine one (l = 0, same instance), and the unfolded one with the lower loss is kept.

Polish: L_rect measures the angles of the observed corners, which pixel noise bends, so its
minimum follows the noise. The L_rect solution therefore starts a maximum-likelihood fit
(`refine_reprojection`): exact rectangles on the ground plus the same 4 parameters, fitted to the
observed corners by reprojection error (soft-L1, ROBUST_PX). On the benchmark's frames with 2 px
of noise this takes the median right-angle error from 3.7 to 2.8 degrees; exact corners are
untouched (both losses are zero there).

Degenerate case: when all footprints share one heading (their edges parallel, up to 90 degrees,
across instances), a stretch of the BEV along that heading keeps every rectangle a rectangle, so
one degree of freedom of (alpha, beta) is unobservable. The head detects it from the spread of the
rectified headings (modulo 90 degrees; below DEGENERATE_SPREAD_DEG, or a single instance) and then
adds, per instance, PRIOR_WEIGHT * log(aspect / prior aspect), aspect = length / width of the
warped footprint and the prior the class's mean l / w from omnigen.priors. In a non-degenerate
frame the prior is not used, so it cannot bias a well-posed solution.

Output frame (the similarity S): the BEV is (right, forward) like omnigen.draw's: footprints are
clockwise seen from above as the contract's corner order says (this fixes the reflection; majority
vote over instances), forward is the direction in which depth (1 / w) grows, or where image rows
decrease when the view is nearly affine, the scale is metres as far as the class priors say (median over instances
of sqrt(prior l * w / footprint area)), the origin is centred across the footprints and at the
nearest footprint point in forward.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from omnigen.priors import PRIORS

FOLD_MARGIN = 1e-3
"""Smallest allowed w_i / max(w) (a depth ratio of 1000 between the nearest and farthest point)."""
FOLD_WEIGHT = 10.0
AREA_FLOOR = 1e-5
"""Smallest allowed footprint area relative to the frame's median footprint area."""
AREA_WEIGHT = 1.0
DEGENERATE_SPREAD_DEG = 8.0
"""Headings (mod 90 deg) spread less than this across instances: the stretch along them is unobservable.
Exact corners give 0 in that case; 8 deg leaves room for 2 px noise (which spreads a shared heading by
about 5 deg median) while random headings spread about 20 deg (docs/bev.md)."""
PRIOR_WEIGHT = 0.1
ROBUST_COS = 0.05
"""Soft-L1 scale of the corner cosines (about 3 degrees): a footprint with a wrong keypoint (a
mislabelled or badly detected corner) is down-weighted instead of bending everyone's rectification."""
SPARSE_FROM = 40
"""Instances above which the polish uses a sparse Jacobian (lsmr steps); below, dense exact steps
converge in far fewer iterations and are faster."""
ROBUST_PX = 3.0
"""Soft-L1 scale of the reprojection polish, in pixels (converted to Hartley units)."""
DEFAULT_CLASS = "car"
DEPTH_GRADIENT_MIN = 0.05
"""Relative spread of 1/w (depth) across the footprints above which it defines forward."""

RIDGE_LAMBDA = 1.0
"""Ridge strength on standardised features (each column of phi z-scored over the frame's keypoint
detections); with N fitted boxes it shrinks W by about lambda / N on well-spread features and keeps
a frame with fewer than six keypoint detections (fewer than phi's 5 dims + bias) well-posed."""


def class_aspect(name: str | None) -> float:
    """Length / width prior of a class (see class_footprint)."""
    length, width = class_footprint(name)
    return length / width


def class_footprint(name: str | None) -> tuple[float, float]:
    """(length, width) prior in metres of a fine class; a coarse target class (vehicle, person, bike)
    takes its most common member's, an unknown name the car's."""
    coarse = {"vehicle": "car", "person": "pedestrian", "bike": "cyclist"}
    name = name if name in PRIORS else coarse.get(name or "", DEFAULT_CLASS)
    m = PRIORS.get(name, PRIORS[DEFAULT_CLASS]).mean
    return m[0], m[1]


@dataclass
class BevResult:
    """The rectification of one image.

    homography: (3, 3) image pixels -> BEV (right, forward) in approximate metres, scaled to unit
    Frobenius norm with the sign that gives footprint points a positive third coordinate.
    footprints: (N, 4, 2) corners 4-7 in the BEV; centres (N, 2); headings (N,) radians of the
    forward axis (rear-edge midpoint to front-edge midpoint), 0 along +right, counter-clockwise.
    residual: L_rect at the solution (sum of squared cosines); angle_error_deg (N,): each
    footprint's largest deviation from a right angle. degenerate: all headings shared, the aspect
    prior was used. iterations: function evaluations of the accepted solves (L_rect, prior,
    polish). folded: a footprint point lies beyond the vanishing line (should never be True;
    reported, not hidden).
    """

    homography: np.ndarray
    footprints: np.ndarray
    centres: np.ndarray
    headings: np.ndarray
    residual: float
    angle_error_deg: np.ndarray
    degenerate: bool
    iterations: int
    init_instance: int
    folded: bool = False

    def to_bev(self, points: np.ndarray) -> np.ndarray:
        return apply_homography(self.homography, points)


# ---------------------------------------------------------------------------------------------
# Small geometry
# ---------------------------------------------------------------------------------------------


def apply_homography(H: np.ndarray, points: np.ndarray) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64)
    flat = pts.reshape(-1, 2)
    q = flat @ H[:, :2].T + H[:, 2]
    return (q[:, :2] / q[:, 2:3]).reshape(pts.shape)


def hartley_normalisation(points: np.ndarray) -> np.ndarray:
    """T with T x: centroid at the origin, mean distance sqrt(2) (Hartley 1997)."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    mean = pts.mean(axis=0)
    dist = np.linalg.norm(pts - mean, axis=1).mean()
    s = math.sqrt(2) / dist if dist > 0 else 1.0
    return np.array([[s, 0, -s * mean[0]], [0, s, -s * mean[1]], [0, 0, 1.0]])


def dlt_homography(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Normalised DLT (HZ algorithm 4.2): both point sets Hartley-normalised, SVD, denormalised."""
    Ts, Td = hartley_normalisation(src), hartley_normalisation(dst)
    s = apply_homography(Ts, src)
    d = apply_homography(Td, dst)
    rows = []
    for (x, y), (u, v) in zip(s, d):
        rows.append([0, 0, 0, -x, -y, -1, v * x, v * y, v])
        rows.append([x, y, 1, 0, 0, 0, -u * x, -u * y, -u])
    _, _, vt = np.linalg.svd(np.asarray(rows))
    Hn = vt[-1].reshape(3, 3)
    return np.linalg.inv(Td) @ Hn @ Ts


def signed_areas(quads: np.ndarray) -> np.ndarray:
    """Shoelace areas of (N, 4, 2) quads; positive counter-clockwise in a y-up frame."""
    x, y = quads[..., 0], quads[..., 1]
    return 0.5 * (x * np.roll(y, -1, axis=-1) - np.roll(x, -1, axis=-1) * y).sum(axis=-1)


def corner_cosines(quads: np.ndarray) -> np.ndarray:
    """(N, 4) cosine of the angle at each corner (between its two edges)."""
    e = np.roll(quads, -1, axis=-2) - quads  # e_k = p_{k+1} - p_k
    n = np.linalg.norm(e, axis=-1)
    n = np.maximum(n, 1e-12 * (1.0 + n.max(initial=0.0)))
    u = e / n[..., None]
    return (u * np.roll(u, 1, axis=-2)).sum(axis=-1)


def right_angle_error_deg(quads: np.ndarray) -> np.ndarray:
    """(N,) largest |corner angle - 90 deg| per quad."""
    c = np.clip(corner_cosines(quads), -1.0, 1.0)
    return np.degrees(np.abs(np.arcsin(c))).max(axis=-1)


def footprint_aspect(quads: np.ndarray) -> np.ndarray:
    """Length (sides 5-6, 7-4) over width (front 4-5, rear 6-7) per quad."""
    e = np.linalg.norm(np.roll(quads, -1, axis=-2) - quads, axis=-1)
    return (e[..., 1] + e[..., 3]) / np.maximum(e[..., 0] + e[..., 2], 1e-12)


def headings_of(quads: np.ndarray) -> np.ndarray:
    front = 0.5 * (quads[..., 0, :] + quads[..., 1, :])
    rear = 0.5 * (quads[..., 2, :] + quads[..., 3, :])
    d = front - rear
    return np.arctan2(d[..., 1], d[..., 0])


def heading_spread_deg(quads: np.ndarray) -> float:
    """Circular spread of the edge directions modulo 90 degrees (0 when all footprints are parallel)."""
    e = quads[..., 1, :] - quads[..., 0, :]
    theta = np.arctan2(e[..., 1], e[..., 0])
    r = float(np.abs(np.exp(4j * theta).mean()))
    return math.degrees(math.sqrt(max(-2.0 * math.log(max(r, 1e-300)), 0.0)) / 4.0)


# ---------------------------------------------------------------------------------------------
# The 4-parameter rectification
# ---------------------------------------------------------------------------------------------


def _affine_matrix(alpha: float, log_beta: float) -> np.ndarray:
    beta = float(_bounded_exp(log_beta))  # the same clamp as _warp, so H is the warp the solver saw
    return np.array([[1.0 / beta, -alpha / beta, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


LOG_BETA_LIMIT = 30.0
"""|log| of a stretch or size beyond this (e^30) is no rectification of a real ground; clamping
keeps the solver's trial steps finite on wild input (poorly trained detectors' corners)."""


def _bounded_exp(x):
    """exp of a log-parameter clamped to +-LOG_BETA_LIMIT (floats or arrays)."""
    return np.exp(np.clip(x, -LOG_BETA_LIMIT, LOG_BETA_LIMIT))


def _projective_matrix(l1: float, l2: float) -> np.ndarray:
    return np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [l1, l2, 1.0]])


def _warp(params: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised points (..., 2) -> (rectified (..., 2), w (...)) under P(l) then A(alpha, beta)."""
    l1, l2, alpha, log_beta = params
    w = 1.0 + l1 * pts[..., 0] + l2 * pts[..., 1]
    safe = np.where(np.abs(w) < 1e-9, 1e-9, w)
    x, y = pts[..., 0] / safe, pts[..., 1] / safe
    beta = float(_bounded_exp(log_beta))  # the solver may probe far out
    return np.stack([(x - alpha * y) / beta, y], axis=-1), w


def _residuals(params: np.ndarray, pts: np.ndarray, prior_aspect: np.ndarray | None,
               weights: np.ndarray) -> np.ndarray:
    quads, w = _warp(params, pts)
    res = [(weights * corner_cosines(quads)).ravel()]
    ratio = w / max(float(w.max()), 1e-12)
    res.append(FOLD_WEIGHT * np.maximum(0.0, FOLD_MARGIN - ratio).ravel())
    area = np.abs(signed_areas(quads))
    rel = area / max(float(np.median(area)), 1e-300)
    res.append(AREA_WEIGHT * np.maximum(0.0, math.log(AREA_FLOOR) - np.log(np.maximum(rel, 1e-300))))
    if prior_aspect is not None:
        res.append(PRIOR_WEIGHT * np.log(np.maximum(footprint_aspect(quads), 1e-12) / prior_aspect))
    return np.concatenate(res)


def _affine_part_for(l: np.ndarray, inst: np.ndarray, rect: np.ndarray) -> tuple[float, float]:
    """alpha, log beta that best map the instance, affinely rectified by P(l), onto the rectangle."""
    w = 1.0 + inst @ l
    x = inst / w[:, None]
    X = np.concatenate([x, np.ones((4, 1))], axis=1)
    M, *_ = np.linalg.lstsq(X, rect, rcond=None)  # rect ~ x @ M[:2] + M[2]
    lin = M[:2].T  # rect ~ lin @ x
    q, r = np.linalg.qr(lin)
    signs = np.sign(np.diag(r))
    signs[signs == 0] = 1
    r = signs[:, None] * r
    if r[0, 0] <= 0 or r[1, 1] <= 0:
        return 0.0, 0.0
    # A = r / r11 = [[1/beta, -alpha/beta], [0, 1]]
    beta = r[1, 1] / r[0, 0]
    alpha = -r[0, 1] / r[0, 0]
    return float(alpha), float(math.log(beta))


def _pull_back(l: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, bool]:
    """Shrink l towards 0 (the vanishing line towards infinity) when it cuts through or grazes the footprints.

    w = 1 + l . x is 1 at the centroid; a start with min w <= 0.05 is scaled back so the worst point
    sits halfway to that bound. Returns (l, pulled back?)."""
    s = pts.reshape(-1, 2) @ l
    if (1.0 + s).min() > 0.05:
        return l, False
    t = min(0.5 * (1.0 - 0.05) / -si for si in s if si < 0)
    return l * t, True


def choose_instance(quads_img: np.ndarray) -> int:
    """The best-conditioned footprint: large and little skewed (area times the worst corner's |sin|)."""
    area = np.abs(signed_areas(quads_img))
    c = np.clip(corner_cosines(quads_img), -1, 1)
    worst_sin = np.sqrt(1.0 - c ** 2).min(axis=1)
    a = signed_areas(quads_img)
    # a convex, simple quad: all corners turn the same way
    e = np.roll(quads_img, -1, axis=1) - quads_img
    cross = e[:, :, 0] * np.roll(e, -1, axis=1)[:, :, 1] - e[:, :, 1] * np.roll(e, -1, axis=1)[:, :, 0]
    convex = (np.sign(cross) == np.sign(a)[:, None]).all(axis=1)
    score = area * worst_sin * np.where(convex, 1.0, 1e-6)
    return int(np.argmax(score))


def _canonical_rectangle(aspect: float) -> np.ndarray:
    """Corners 4-7 of a rectangle of length aspect and width 1 in (forward, left), the contract's order."""
    L, W = aspect / 2.0, 0.5
    return np.array([[L, W], [L, -W], [-L, -W], [-L, W]])


def _solve(pts: np.ndarray, x0: np.ndarray, prior: np.ndarray | None,
           weights: np.ndarray) -> tuple[np.ndarray, float, int, bool]:
    from scipy.optimize import least_squares  # here: importing it takes ~0.3 s, which `omnigen --help` would pay

    sol = least_squares(_residuals, x0, args=(pts, prior, weights), method="trf", x_scale="jac",
                        loss="soft_l1", f_scale=ROBUST_COS,
                        xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=400)
    _, w = _warp(sol.x, pts)
    folded = bool((w <= 0).any())
    return sol.x, float(2.0 * sol.cost), int(sol.nfev), folded


def rectify(ground_xy: np.ndarray, classes: Sequence[str | None] | None = None,
            init_instance: int | None = None, refine: bool = True, jacobian: str = "exact") -> BevResult:
    """The BEV of one image from its detections' ground corners (N, 4, 2) in pixels (corners 4-7).

    `classes` name each detection's class for the aspect and size priors (None: car).
    `init_instance` forces the instance of the DLT start (tests); by default the best-conditioned one.
    `refine` polishes the L_rect solution by reprojection error (`refine_reprojection`, whose
    `jacobian` this passes on).
    """
    quads = np.asarray(ground_xy, dtype=np.float64)
    if quads.ndim != 3 or quads.shape[1:] != (4, 2) or len(quads) == 0:
        raise ValueError(f"ground corners must be (N, 4, 2) with N >= 1, got {quads.shape}")
    if not np.isfinite(quads).all():
        raise ValueError("ground corners must be finite")
    n = len(quads)
    classes = list(classes) if classes is not None else [None] * n
    aspects = np.array([class_aspect(c) for c in classes])

    T = hartley_normalisation(quads.reshape(-1, 2))
    pts = apply_homography(T, quads)
    weights = np.ones((n, 4))  # per-corner weights; uniform (edge-length weights measured worse, docs/bev.md)
    k = choose_instance(quads) if init_instance is None else int(init_instance)
    rect = _canonical_rectangle(aspects[k])
    Hn = dlt_homography(pts[k], rect)
    l0 = Hn[2, :2] / Hn[2, 2]
    l0, _ = _pull_back(l0, pts)
    starts = [np.concatenate([l0, _affine_part_for(l0, pts[k], rect)])]
    zero = np.zeros(2)
    starts.append(np.concatenate([zero, _affine_part_for(zero, pts[k], rect)]))

    best = None
    for x0 in starts:
        x, cost, nfev, folded = _solve(pts, x0, None, weights)
        if best is None or (folded, cost) < best[0]:
            best = ((folded, cost), x, nfev)
    _, x, nfev = best

    quads_r, _ = _warp(x, pts)
    degenerate = n == 1 or heading_spread_deg(quads_r) < DEGENERATE_SPREAD_DEG
    if degenerate:
        x, _, nfev2, _ = _solve(pts, x, aspects, weights)
        nfev += nfev2

    if refine and n >= 2:
        x, nfev3 = refine_reprojection(x, pts, aspects if degenerate else None, px_scale=T[0, 0], jacobian=jacobian)
        nfev += nfev3

    H = _affine_matrix(x[2], x[3]) @ _projective_matrix(x[0], x[1]) @ T
    S = _canonical_frame(H, quads, classes)
    H = S @ H
    fp = apply_homography(H, quads)
    # sign: footprint points get a positive third coordinate
    wsum = (quads.reshape(-1, 2) @ H[2, :2] + H[2, 2]).sum()
    H = H / np.linalg.norm(H) * (1.0 if wsum > 0 else -1.0)
    w_all = quads.reshape(-1, 2) @ H[2, :2] + H[2, 2]
    return BevResult(homography=H, footprints=fp, centres=fp.mean(axis=1), headings=headings_of(fp),
                     residual=float((corner_cosines(fp) ** 2).sum()), angle_error_deg=right_angle_error_deg(fp),
                     degenerate=bool(degenerate), iterations=nfev, init_instance=k, folded=bool((w_all <= 0).any()))


def _unwarp(params: np.ndarray, rect: np.ndarray) -> np.ndarray:
    """Rectified points (..., 2) -> normalised image points: the inverse of `_warp`."""
    l1, l2, alpha, log_beta = params
    beta = float(_bounded_exp(log_beta))
    a = np.stack([beta * rect[..., 0] + alpha * rect[..., 1], rect[..., 1]], axis=-1)
    w = 1.0 - l1 * a[..., 0] - l2 * a[..., 1]
    w = np.where(np.abs(w) < 1e-9, 1e-9, w)
    return a / w[..., None]


_UNIT_RECT = np.array([[0.5, 0.5], [0.5, -0.5], [-0.5, -0.5], [-0.5, 0.5]])  # corners 4-7, (forward, left)


def _rectangles(inst: np.ndarray, handedness: float = 1.0) -> np.ndarray:
    """(N, 5) [cx, cy, heading, log length, log width] -> (N, 4, 2) corners 4-7 in the rectified frame.

    handedness -1: the rectified frame is a mirror image of the ground (left is clockwise of forward).
    """
    cx, cy, th, ll, lw = inst.T
    local = _UNIT_RECT[None] * np.stack([_bounded_exp(ll), handedness * _bounded_exp(lw)], axis=-1)[:, None, :]
    c, s = np.cos(th)[:, None], np.sin(th)[:, None]
    return np.stack([cx[:, None] + c * local[..., 0] - s * local[..., 1],
                     cy[:, None] + s * local[..., 0] + c * local[..., 1]], axis=-1)


def refine_reprojection(x: np.ndarray, pts: np.ndarray, prior_aspect: np.ndarray | None,
                        px_scale: float = 1.0, jacobian: str = "exact") -> tuple[np.ndarray, int]:
    """Maximum-likelihood polish: true rectangles on the ground and the 4 rectification parameters,
    fitted jointly to the observed corners by their reprojection error.

    L_rect measures the angles of the *observed* corners, which noise bends; with 2 px of noise on
    footprints a few tens of pixels deep, its minimum follows the noise (median 3.7 deg off a right
    angle on benchmarks/bench_bev.py's 200 frames). Under isotropic Gaussian pixel noise the
    likelihood is the reprojection error of exact rectangles (HZ's "gold standard" for
    homographies), so the L_rect solution starts this fit: per instance a centre, heading, log
    length and log width in the rectified frame (5 N + 4 unknowns, 8 N residuals; a sparse Jacobian
    above SPARSE_FROM instances). Soft-L1 at ROBUST_PX pixels (`px_scale` converts pixels to the
    normalised units of `pts`). In the degenerate case a weak aspect prior pins the stretch. A
    polish that ends folded or non-finite is discarded and the L_rect solution returned.

    `jacobian` "exact" (`_reprojection_jacobian`) or scipy's "2-point" finite differences, which
    give the same solution (tests/detector/test_bev.py, benchmarks/bench_bev.py) 4 + 5 N times
    slower a step.
    """
    if jacobian not in ("exact", "2-point"):
        raise ValueError(f"jacobian must be 'exact' or '2-point', got {jacobian!r}")
    quads, _ = _warp(x, pts)
    e = np.linalg.norm(np.roll(quads, -1, axis=1) - quads, axis=-1)
    inst0 = np.stack([quads[..., 0].mean(1), quads[..., 1].mean(1), headings_of(quads),
                      np.log(np.maximum(0.5 * (e[:, 1] + e[:, 3]), 1e-12)),
                      np.log(np.maximum(0.5 * (e[:, 0] + e[:, 2]), 1e-12))], axis=1)
    n = len(pts)
    handedness = -1.0 if np.sum(np.sign(signed_areas(quads))) > 0 else 1.0

    def residuals(theta: np.ndarray) -> np.ndarray:
        g, inst = theta[:4], theta[4:].reshape(n, 5)
        res = [(_unwarp(g, _rectangles(inst, handedness)) - pts).ravel()]
        if prior_aspect is not None:
            res.append(0.01 * (inst[:, 3] - inst[:, 4] - np.log(prior_aspect)))
        return np.concatenate(res)

    def exact(theta: np.ndarray):
        J = _reprojection_jacobian(theta[:4], theta[4:].reshape(n, 5), handedness, prior_aspect is not None)
        if n <= SPARSE_FROM:
            return J
        from scipy.sparse import csr_matrix

        return csr_matrix(J)

    theta0 = np.concatenate([x, inst0.ravel()])
    from scipy.optimize import least_squares  # here, as in _solve

    if jacobian == "exact":
        jac, sparsity = exact, None
    else:
        jac, sparsity = "2-point", _reprojection_sparsity(n, prior_aspect is not None) if n > SPARSE_FROM else None
    sol = least_squares(residuals, theta0, jac=jac, jac_sparsity=sparsity, method="trf", x_scale="jac",
                        loss="soft_l1", f_scale=ROBUST_PX * px_scale,
                        xtol=1e-10, ftol=1e-10, max_nfev=200)
    _, w = _warp(sol.x[:4], pts)
    if (w <= 0).any() or not np.isfinite(sol.x).all():
        return x, int(sol.nfev)
    return sol.x[:4], int(sol.nfev)


def _reprojection_sparsity(n: int, with_prior: bool) -> np.ndarray:
    """Which residuals of `refine_reprojection` each parameter moves (for finite differences)."""
    rows = 8 * n + (n if with_prior else 0)
    sparsity = np.zeros((rows, 4 + 5 * n), dtype=bool)
    sparsity[:, :4] = True
    for i in range(n):
        sparsity[8 * i:8 * i + 8, 4 + 5 * i:9 + 5 * i] = True
        if with_prior:
            sparsity[8 * n + i, 4 + 5 * i:9 + 5 * i] = True
    return sparsity


def _clipped_exp_slope(x: np.ndarray) -> np.ndarray:
    """d/dx of `_bounded_exp`: exp inside the clamp, 0 outside it (where the clamp holds it flat)."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(np.abs(x) <= LOG_BETA_LIMIT, np.exp(np.clip(x, -LOG_BETA_LIMIT, LOG_BETA_LIMIT)), 0.0)


def _reprojection_jacobian(g: np.ndarray, inst: np.ndarray, handedness: float, with_prior: bool) -> np.ndarray:
    """The exact Jacobian of `refine_reprojection`'s residuals: d(image corners, prior) / d(g, inst).

    The residuals' rows are each instance's 8 corner coordinates (then one prior row per instance);
    the columns are the 4 rectification parameters g = (l1, l2, alpha, log beta), then each
    instance's (cx, cy, heading, log length, log width). Finite differences needed 4 + 5 N residual
    evaluations per step, which made the polish the slowest part of `omnigen bev`; this costs about
    one. The chain is rectangle -> affine -> projective (`_rectangles`, then `_unwarp`); where
    `_unwarp` guards |w| < 1e-9 the guarded w is held constant, as the residuals hold it.
    """
    n = len(inst)
    l1, l2, alpha, log_beta = g
    beta = float(_bounded_exp(log_beta))
    dbeta = float(_clipped_exp_slope(log_beta))
    cx, cy, th, ll, lw = inst.T
    el, ew = _bounded_exp(ll), handedness * _bounded_exp(lw)
    lx = _UNIT_RECT[None, :, 0] * el[:, None]  # (n, 4)
    ly = _UNIT_RECT[None, :, 1] * ew[:, None]
    c, s = np.cos(th)[:, None], np.sin(th)[:, None]
    rx, ry = cx[:, None] + c * lx - s * ly, cy[:, None] + s * lx + c * ly
    # d(rx, ry) / d(cx, cy, th, ll, lw): (n, 4, 2, 5)
    dlx_dll = _UNIT_RECT[None, :, 0] * _clipped_exp_slope(ll)[:, None]
    dly_dlw = _UNIT_RECT[None, :, 1] * handedness * _clipped_exp_slope(lw)[:, None]
    zeros, ones = np.zeros_like(rx), np.ones_like(rx)
    dr = np.stack([np.stack([ones, zeros, -s * lx - c * ly, c * dlx_dll, -s * dly_dlw], axis=-1),
                   np.stack([zeros, ones, c * lx - s * ly, s * dlx_dll, c * dly_dlw], axis=-1)], axis=2)
    a0, a1 = beta * rx + alpha * ry, ry
    w = 1.0 - l1 * a0 - l2 * a1
    live = np.abs(w) >= 1e-9
    w = np.where(live, w, 1e-9)
    a = np.stack([a0, a1], axis=-1)  # (n, 4, 2)
    l = np.array([l1, l2])
    # dp/da = I / w + a l^T / w^2 ; dp/dl = a a^T / w^2 (w held constant where it is guarded)
    gate = live[..., None, None]
    dp_da = np.eye(2) / w[..., None, None] + gate * a[..., :, None] * l[None, None, None, :] / (w ** 2)[..., None, None]
    dp_dl = gate * a[..., :, None] * a[..., None, :] / (w ** 2)[..., None, None]
    # da/d(alpha, log beta) and da/d(rx, ry)
    da_dg = np.zeros((n, 4, 2, 2))
    da_dg[..., 0, 0], da_dg[..., 0, 1] = ry, dbeta * rx
    da_dr = np.array([[beta, alpha], [0.0, 1.0]])
    dp_dg = np.concatenate([dp_dl, dp_da @ da_dg], axis=-1)  # (n, 4, 2, 4)
    dp_dinst = dp_da @ da_dr @ dr  # (n, 4, 2, 5)
    rows = 8 * n + (n if with_prior else 0)
    J = np.zeros((rows, 4 + 5 * n))
    J[:8 * n, :4] = dp_dg.reshape(8 * n, 4)
    idx = np.arange(n)
    block = dp_dinst.reshape(n, 8, 5)
    r_idx = (8 * idx[:, None, None] + np.arange(8)[None, :, None])
    c_idx = (4 + 5 * idx[:, None, None] + np.arange(5)[None, None, :])
    J[r_idx, c_idx] = block
    if with_prior:
        J[8 * n + idx, 4 + 5 * idx + 3] = 0.01
        J[8 * n + idx, 4 + 5 * idx + 4] = -0.01
    return J


def _canonical_frame(H: np.ndarray, quads_img: np.ndarray, classes: Sequence[str | None]) -> np.ndarray:
    """The similarity S that puts the rectified plane in the (right, forward) metre frame (module doc)."""
    fp = apply_homography(H, quads_img)
    S = np.eye(3)
    # reflection: the contract's corners 4-7 run clockwise seen from above (negative shoelace, y up)
    if np.sum(np.sign(signed_areas(fp))) > 0:
        S = np.diag([-1.0, 1.0, 1.0]) @ S
    fp = apply_homography(S @ H, quads_img)
    # rotation: forward = the direction in which depth grows. Depth is proportional to 1 / w
    # (w = the third homogeneous coordinate) and is an affine function of position on the ground,
    # so a linear fit gives its gradient exactly. A nearly affine view (vanishing line far away,
    # 1/w almost constant) has no usable depth gradient: there forward is where image rows decrease.
    pts = fp.reshape(-1, 2)
    img = quads_img.reshape(-1, 2)
    X = np.concatenate([pts, np.ones((len(pts), 1))], axis=1)
    inv_w = 1.0 / np.abs(img @ H[2, :2] + H[2, 2])
    if np.ptp(inv_w) > DEPTH_GRADIENT_MIN * inv_w.mean():
        g = np.linalg.lstsq(X, inv_w, rcond=None)[0][:2]
    else:
        g = np.linalg.lstsq(X, -img[:, 1], rcond=None)[0][:2]
    if np.linalg.norm(g) > 0:
        ang = math.atan2(g[1], g[0])
        rot = math.pi / 2 - ang
        c, s = math.cos(rot), math.sin(rot)
        S = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]) @ S
    fp = apply_homography(S @ H, quads_img)
    # scale: metres from the class footprint priors
    area = np.abs(signed_areas(fp))
    prior_area = np.array([np.prod(class_footprint(c)) for c in classes])
    ok = area > 0
    scale = float(np.median(np.sqrt(prior_area[ok] / area[ok]))) if ok.any() else 1.0
    S = np.diag([scale, scale, 1.0]) @ S
    fp = apply_homography(S @ H, quads_img)
    pts = fp.reshape(-1, 2)
    tx = -0.5 * (pts[:, 0].min() + pts[:, 0].max())
    ty = -pts[:, 1].min()
    return np.array([[1, 0, tx], [0, 1, ty], [0, 0, 1.0]]) @ S


# ---------------------------------------------------------------------------------------------
# 2D-only boxes: the ridge map
# ---------------------------------------------------------------------------------------------


def box_features(boxes_xywh: np.ndarray) -> np.ndarray:
    """phi(b) = [cx, cy, w, h, w/h] of COCO [x, y, w, h] boxes."""
    b = np.asarray(boxes_xywh, dtype=np.float64).reshape(-1, 4)
    w, h = b[:, 2], b[:, 3]
    return np.stack([b[:, 0] + w / 2, b[:, 1] + h / 2, w, h, w / np.maximum(h, 1e-9)], axis=1)


@dataclass(frozen=True)
class RidgeMap:
    """c = W (phi - mu) / sigma + c_mean: a bias term (unpenalised) and standardised features."""

    W: np.ndarray  # (2, 5)
    mu: np.ndarray
    sigma: np.ndarray
    bias: np.ndarray

    def __call__(self, boxes_xywh: np.ndarray) -> np.ndarray:
        z = (box_features(boxes_xywh) - self.mu) / self.sigma
        return z @ self.W.T + self.bias


def fit_ridge(boxes_xywh: np.ndarray, centres: np.ndarray, lam: float = RIDGE_LAMBDA) -> RidgeMap:
    """W* = argmin sum ||c - W phi(b)||^2 + lam ||W||^2, closed form (Z^T Z + lam I)^-1 Z^T C.

    With a bias: phi is centred (the intercept is the mean centre, not shrunk, since the BEV origin
    is a convention) and scaled to unit spread so that one lambda suits pixels and ratios alike.
    """
    phi = box_features(boxes_xywh)
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 2)
    if len(phi) != len(c) or len(c) == 0:
        raise ValueError("ridge fit needs as many centres as boxes, at least one")
    mu = phi.mean(axis=0)
    sigma = phi.std(axis=0)
    sigma = np.where(sigma > 1e-9, sigma, 1.0)
    z = (phi - mu) / sigma
    bias = c.mean(axis=0)
    W = np.linalg.solve(z.T @ z + lam * np.eye(z.shape[1]), z.T @ (c - bias)).T
    return RidgeMap(W, mu, sigma, bias)
