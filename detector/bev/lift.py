"""Metric 3D from keypoints: class dimension priors, PnP lifting, ground adherence, KITTI lines.

The detector predicts the eight projected cuboid corners and never sees the camera. A metric box
needs two things the image alone does not give: the object's size (here the median size of its
class in the training split, `DimensionPriors`) and the intrinsics K (given at evaluation only).
With both, the corners' object-frame positions are known (CORNER_SIGNS * dims / 2) and the pose
that maps them onto the predicted pixels is a Perspective-n-Point problem, solved by OpenCV.

Why SQPnP then Levenberg-Marquardt: SQPnP is a globally optimal, non-iterative solver for any
number of points >= 3 (no initial guess, no flipped local minimum as iterative solvers can fall
into); the LM refinement then minimises the reprojection error proper, which is what a
keypoint detector's errors are measured in. The full method is documented in docs/metric-3d.md.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import cv2
import numpy as np

from omnigen.conventions import FINE_CLASSES, NEAR_PLANE, NUM_KEYPOINTS
from omnigen.dataset import Dataset
from omnigen.formats.kitti import box_to_kitti, kitti_alpha, kitti_number, kitti_type
from omnigen.geometry import Box3D, cuboid_corners, local_corners
from omnigen.priors import PRIORS

MIN_POINTS = 4
"""Corners a box needs for a lift: 4 non-coplanar points fix a pose with known dims without the
ambiguities of the 3-point case."""

BOTTOM_EDGES: tuple[tuple[int, int], ...] = ((4, 5), (5, 6), (6, 7), (7, 4))
"""The ground-contact face's four edges (0-based corner pairs)."""



# ---------------------------------------------------------------------------------------------
# Dimension priors
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DimensionPriors:
    """Per fine class, the median [l, w, h] (metres, object frame: x forward, y left, z up).

    `counts` holds how many training objects each median came from; a class with none falls
    back to omnigen/priors.py's mean (count 0), so every fine class always has a size.
    Medians rather than means: a few mislabelled or swapped-dimension boxes do not move them.
    """

    dims: dict[str, tuple[float, float, float]]
    counts: dict[str, int]

    def __post_init__(self) -> None:
        missing = [c for c in FINE_CLASSES if c not in self.dims]
        if missing:
            raise ValueError(f"dimension priors miss the classes {missing}")

    def dims_for(self, category_names: Sequence[str]) -> np.ndarray:
        """(N, 3) [l, w, h] of each name; an unknown name is an error naming it."""
        out = np.empty((len(category_names), 3), dtype=np.float64)
        for i, name in enumerate(category_names):
            try:
                out[i] = self.dims[name]
            except KeyError:
                raise KeyError(f"no dimension prior for class {name!r} (fine classes: {', '.join(FINE_CLASSES)})") from None
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"dims_order": ["l", "w", "h"],
                "classes": {c: {"dims": list(self.dims[c]), "count": int(self.counts.get(c, 0))} for c in FINE_CLASSES}}

    @classmethod
    def from_dict(cls, d: dict[str, Any], file: str = "<priors>") -> "DimensionPriors":
        classes = d.get("classes") if isinstance(d, dict) else None
        if not isinstance(classes, dict):
            raise ValueError(f"{file}: field 'classes' must be a table of class -> {{dims, count}}")
        dims, counts = {}, {}
        for name, entry in classes.items():
            if name not in FINE_CLASSES:
                raise ValueError(f"{file}: field 'classes.{name}': not a fine class")
            values = entry.get("dims") if isinstance(entry, dict) else None
            if not (isinstance(values, list) and len(values) == 3 and all(isinstance(v, (int, float)) and v > 0 for v in values)):
                raise ValueError(f"{file}: field 'classes.{name}.dims' must be three positive numbers [l, w, h]")
            dims[name] = tuple(float(v) for v in values)
            counts[name] = int(entry.get("count", 0))
        for c in FINE_CLASSES:  # files written before a class existed: the fixed prior
            if c not in dims:
                dims[c], counts[c] = tuple(PRIORS[c].mean), 0
        return cls(dims, counts)


def fit_dimension_priors(ds: Dataset, frame_ids: list[str] | None = None) -> DimensionPriors:
    """Median [l, w, h] per fine class over the objects of `frame_ids` (all frames when None).

    Pass the training split's frame ids: priors fitted on the frames that are evaluated would
    leak the answer into the lifting. `ds.objects.dims` is already [l, w, h] for every source.
    """
    t = ds.objects
    rows = np.ones(len(t), dtype=bool)
    if frame_ids is not None:
        frames = np.array([ds.index_of(f) for f in frame_ids], dtype=np.int64)
        rows = np.isin(t.frame, frames)
    rows &= np.isfinite(t.dims).all(axis=1)
    dims, counts = {}, {}
    for k, name in enumerate(FINE_CLASSES):
        sel = t.dims[rows & (t.category == k)]
        counts[name] = int(len(sel))
        dims[name] = tuple(float(v) for v in np.median(sel, axis=0)) if len(sel) else tuple(PRIORS[name].mean)
    return DimensionPriors(dims, counts)


# ---------------------------------------------------------------------------------------------
# Lifting
# ---------------------------------------------------------------------------------------------


@dataclass
class LiftedBoxes:
    """N boxes recovered by PnP, in the camera frame of K (OpenCV: x right, y down, z forward).

    R: (N, 3, 3) object -> camera (columns: forward, left, up); t: (N, 3) box centres; dims
    (N, 3) [l, w, h] used for the lift; ok: (N,) False where the lift failed, had too few
    corners or put the box behind the camera (R, t are NaN there); reproj_px: (N,) RMS
    reprojection error of the corners used, in pixels.
    """

    R: np.ndarray
    t: np.ndarray
    dims: np.ndarray
    ok: np.ndarray
    reproj_px: np.ndarray

    def __len__(self) -> int:
        return len(self.ok)

    def corners(self) -> np.ndarray:
        """(N, 8, 3) camera-frame corners in the contract's order (NaN where not ok)."""
        return cuboid_corners(self.t, self.dims, self.R)

    def box(self, i: int) -> Box3D:
        return Box3D(self.t[i], self.dims[i], self.R[i])


def object_corners(dims: np.ndarray) -> np.ndarray:
    """(N, 8, 3) corners in the object frame: CORNER_SIGNS * dims / 2 (geometry.local_corners)."""
    return local_corners(np.asarray(dims, dtype=np.float64).reshape(-1, 3))


REFINE_CRITERIA = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 20, 1e-10)
"""Levenberg-Marquardt stopping rule: OpenCV's default (machine-epsilon steps) runs its 20
iterations out on every box; steps below 1e-10 change nothing a pixel can see, at a third the cost."""


def _solve_one(obj: np.ndarray, img: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(rvec, tvec) for one box, or None when OpenCV finds no pose."""
    try:
        found, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_SQPNP)
        if not found:
            return None
        return cv2.solvePnPRefineLM(obj, img, K, None, rvec, tvec, REFINE_CRITERIA)
    except cv2.error:
        return None


def lift_keypoints(keypoints: np.ndarray, dims: np.ndarray, K: np.ndarray,
                   valid: np.ndarray | None = None) -> LiftedBoxes:
    """Recover camera-frame boxes from their projected corners and known sizes.

    keypoints (N, 8, 2) pixels in the contract's order; dims (N, 3) [l, w, h]; K (3, 3).
    `valid` (N, 8) says which corners to use (default: every finite one); a box needs
    MIN_POINTS of them. Corners of a box the detector placed are all usable, even occluded or
    outside the image: they are the cuboid's geometry, not its visible pixels.
    """
    # Contiguous copies: OpenCV reads a strided view (x, y sliced out of x, y, v rows) wrongly.
    kp = np.ascontiguousarray(np.asarray(keypoints, dtype=np.float64).reshape(-1, NUM_KEYPOINTS, 2))
    dims = np.asarray(dims, dtype=np.float64).reshape(-1, 3)
    K = np.ascontiguousarray(np.asarray(K, dtype=np.float64).reshape(3, 3))
    if len(dims) != len(kp):
        raise ValueError(f"lift_keypoints: {len(kp)} keypoint sets but {len(dims)} dims")
    use = np.isfinite(kp).all(axis=2)
    if valid is not None:
        use &= np.asarray(valid, dtype=bool).reshape(-1, NUM_KEYPOINTS)
    n = len(kp)
    R = np.full((n, 3, 3), np.nan)
    t = np.full((n, 3), np.nan)
    local = object_corners(dims)
    solvable = (use.sum(axis=1) >= MIN_POINTS) & np.isfinite(dims).all(axis=1) & (dims > 0).all(axis=1)
    full = use.all(axis=1)
    for i in np.flatnonzero(solvable).tolist():  # one OpenCV call per box: the cost is in there
        if full[i]:
            obj, img = local[i], kp[i]
        else:
            obj, img = np.ascontiguousarray(local[i][use[i]]), np.ascontiguousarray(kp[i][use[i]])
        pose = _solve_one(obj, img, K)
        if pose is not None:
            R[i] = cv2.Rodrigues(pose[0])[0]
            t[i] = pose[1].ravel()
    # Behind the camera: a mirrored solution, not a box the camera can see.
    ok = np.isfinite(t).all(axis=1) & (np.nan_to_num(t[:, 2], nan=-1.0) > NEAR_PLANE)
    R[~ok], t[~ok] = np.nan, np.nan
    cam = np.einsum("nij,nkj->nki", R, local) + t[:, None, :]
    uv = cam @ K.T
    uv = uv[..., :2] / uv[..., 2:3]
    sq = np.where(use, np.sum((uv - kp) ** 2, axis=2), 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        err = np.sqrt(sq.sum(axis=1) / use.sum(axis=1))
    err[~ok] = np.nan
    return LiftedBoxes(R=R, t=t, dims=dims.copy(), ok=ok, reproj_px=err)


# ---------------------------------------------------------------------------------------------
# Ground adherence
# ---------------------------------------------------------------------------------------------


def ground_adherence_deg(lifted: LiftedBoxes, plane: np.ndarray) -> np.ndarray:
    """(N,) mean angle in degrees between each box's 4 bottom edges and the ground plane.

    plane: (4,) or (N, 4) [n, d] with n . X + d = 0 in the camera frame (omnigen.geometry.Plane,
    the records' ground_plane); n need not be unit length. An edge lying in a plane parallel to
    the ground scores 0; per edge the angle is asin(|e . n| / |e| |n|). NaN where not ok.
    """
    plane = np.asarray(plane, dtype=np.float64)
    normal = np.broadcast_to(plane[..., :3], (len(lifted), 3))
    normal = normal / np.linalg.norm(normal, axis=-1, keepdims=True)
    corners = lifted.corners()
    angles = []
    for a, b in BOTTOM_EDGES:
        e = corners[:, b] - corners[:, a]
        s = np.abs(np.sum(e * normal, axis=1)) / np.linalg.norm(e, axis=1)
        angles.append(np.degrees(np.arcsin(np.clip(s, 0.0, 1.0))))
    out = np.mean(angles, axis=0)
    out[~lifted.ok] = np.nan
    return out


# ---------------------------------------------------------------------------------------------
# KITTI label lines
# ---------------------------------------------------------------------------------------------


def to_kitti_lines(lifted: LiftedBoxes, category_names: Sequence[str], boxes2d: np.ndarray,
                   scores: np.ndarray | None = None, truncated: np.ndarray | None = None,
                   occluded: np.ndarray | None = None) -> list[str]:
    """KITTI label lines (no trailing newline) for the boxes that lifted; the others are skipped.

    Fields: type, truncated (-1 unless given), occluded (-1 unless given), alpha, the 2D box
    `boxes2d` (N, 4) [x1, y1, x2, y2], h w l, the bottom-centre location x y z in the camera
    frame, rotation_y, and `score` when scores are given (a results file; without scores the
    line is a 15-field label), written as omnigen.formats.kitti writes every KITTI label (names,
    numbers). Location and rotation_y follow formats.kitti.box_to_kitti, the rule of `omnigen
    export kitti`: location = centre + (0, h/2, 0) along the camera's y and
    rotation_y = the heading of the forward axis projected onto the camera's x-z plane, so for a
    pitched camera KITTI tools get the true centre back while the tilt is lost. Every K passed
    here is the image's own camera (P2 = [K | 0] in the exported calib), so no camera offset.
    """
    boxes2d = np.asarray(boxes2d, dtype=np.float64).reshape(-1, 4)
    if len(category_names) != len(lifted) or len(boxes2d) != len(lifted):
        raise ValueError("to_kitti_lines: lifted boxes, category names and 2D boxes differ in number")
    lines = []
    for i in np.flatnonzero(lifted.ok):
        h, w, l, x, y, z, ry = box_to_kitti(lifted.box(i))
        trunc = -1.0 if truncated is None else float(truncated[i])
        occ = -1 if occluded is None else int(occluded[i])
        numbers = [kitti_alpha(ry, x, z), *boxes2d[i], h, w, l, x, y, z, ry]
        if scores is not None:
            numbers.append(float(scores[i]))
        lines.append(f"{kitti_type(category_names[i])} {kitti_number(trunc)} {occ} "
                     + " ".join(kitti_number(v) for v in numbers))
    return lines


__all__ = ["DimensionPriors", "LiftedBoxes", "fit_dimension_priors", "lift_keypoints", "ground_adherence_deg",
           "to_kitti_lines", "object_corners", "BOTTOM_EDGES", "MIN_POINTS"]
