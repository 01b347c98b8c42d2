"""Cuboids, their projection and ground planes in the contract's frames (numpy only, plus shapely for 2D).

Frames: the camera is OpenCV's (x right, y down, z forward); an object's frame has x forward
(length l), y left (width w), z up (height h) with its origin at the cuboid's centre. Pixels
follow OpenCV/KITTI: the centre of the top-left pixel is (0, 0), so an image W wide spans
x in [-0.5, W - 0.5].

Only generic maths lives here (rotations, the cuboid, projection and clipping, silhouettes, planes):
each outside format's conventions are in omnigen.formats (KITTI's boxes in formats.kitti,
DAIR-V2X's in formats.dair), built on these; the camera (K, R, t and the image size as one
type) and its conversions to the renderers' frames (OpenGL, Blender) are in omnigen.camera.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import Polygon, box as shapely_box

from omnigen.conventions import CORNER_SIGNS, NEAR_PLANE, SKELETON

# ---------------------------------------------------------------------------------------------
# Rotations
# ---------------------------------------------------------------------------------------------


def rot_x(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], dtype=np.float64)


def rot_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], dtype=np.float64)


def rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], dtype=np.float64)


def is_rotation(r: np.ndarray, tol: float = 1e-6) -> bool:
    """True for a proper rotation (orthonormal, determinant +1)."""
    r = np.asarray(r, dtype=np.float64)
    if r.shape != (3, 3):
        return False
    gram = r.T @ r
    gram.flat[::4] -= 1.0
    if float(np.abs(gram).max()) > tol:
        return False
    (a, b, c), (d, e, f), (g, h, i) = r.tolist()  # orthonormal: only the determinant's sign is left
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) > 0


def wrap_angle(a: float) -> float:
    """The angle a wrapped to [-pi, pi)."""
    return (a + math.pi) % (2 * math.pi) - math.pi


# ---------------------------------------------------------------------------------------------
# The cuboid
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Box3D:
    """A cuboid in a camera frame.

    center: (3,) metres; dims: (3,) = [l, w, h]; rotation: (3, 3) mapping object-frame vectors
    into the camera frame (columns: forward, left, up). A full rotation, not a yaw, because pole
    and drone cameras are pitched and an object's up is then not the camera's -y.
    """

    center: np.ndarray
    dims: np.ndarray
    rotation: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", np.asarray(self.center, dtype=np.float64).reshape(3))
        object.__setattr__(self, "dims", np.asarray(self.dims, dtype=np.float64).reshape(3))
        object.__setattr__(self, "rotation", np.asarray(self.rotation, dtype=np.float64).reshape(3, 3))

    @property
    def forward(self) -> np.ndarray:
        return self.rotation[:, 0]

    @property
    def left(self) -> np.ndarray:
        return self.rotation[:, 1]

    @property
    def up(self) -> np.ndarray:
        return self.rotation[:, 2]

    def corners(self) -> np.ndarray:
        """(8, 3) corners in the camera frame, in the contract's order (0-3 top, 4-7 bottom)."""
        return cuboid_corners(self.center, self.dims, self.rotation)

    def transformed(self, rotation: np.ndarray, translation: np.ndarray) -> "Box3D":
        """The same cuboid expressed in another frame: X' = rotation @ X + translation."""
        rotation = np.asarray(rotation, dtype=np.float64)
        return Box3D(rotation @ self.center + np.asarray(translation, dtype=np.float64), self.dims, rotation @ self.rotation)

    def bottom_center(self) -> np.ndarray:
        """Centre of the ground-contact face."""
        return self.center - self.up * self.dims[2] / 2.0


def local_corners(dims: np.ndarray) -> np.ndarray:
    """Corners in the object frame, in the contract's order: dims (..., 3) [l, w, h] -> (..., 8, 3)."""
    return CORNER_SIGNS * (np.asarray(dims, dtype=np.float64)[..., None, :] / 2.0)


def cuboid_corners(center: np.ndarray, dims: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """The corners of one cuboid or of many, in the contract's order (0-3 top, 4-7 bottom).

    center (..., 3), dims (..., 3) [l, w, h], rotation (..., 3, 3) object -> frame; returns
    (..., 8, 3): (8, 3) for one box, (N, 8, 3) for N. The one place corners are computed (Box3D,
    the converters, the raster backend's culling, the lifting all call it). Every box goes through
    the same 8x3 @ 3x3 product whether it comes alone or in a batch, so a box's corners are bit
    for bit the same either way, and records written one object at a time or a frame at once agree.
    """
    rotation = np.asarray(rotation, dtype=np.float64)
    center = np.asarray(center, dtype=np.float64)
    return local_corners(dims) @ np.swapaxes(rotation, -1, -2) + center[..., None, :]


def rots_z(yaws: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rot_z of N angles, entry for entry: cosine and sine from math, as rot_z's."""
    yaws = np.asarray(yaws, dtype=np.float64).reshape(-1).tolist()
    c = [math.cos(a) for a in yaws]
    s = [math.sin(a) for a in yaws]
    r = np.zeros((len(yaws), 3, 3))
    r[:, 0, 0] = c
    r[:, 0, 1] = [-v for v in s]
    r[:, 1, 0] = s
    r[:, 1, 1] = c
    r[:, 2, 2] = 1.0
    return r


# ---------------------------------------------------------------------------------------------
# Projection
# ---------------------------------------------------------------------------------------------


def project_points(K: np.ndarray, points: np.ndarray, near: float = NEAR_PLANE) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole projection u = K X.

    Returns (uv, behind): uv is (N, 2) with NaN wherever the point is closer than `near` along
    the optical axis, so a point behind the camera is never mirrored into the image.
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    behind = points[:, 2] < near
    proj = points @ np.asarray(K, dtype=np.float64).T
    depth = np.where(behind, 1.0, proj[:, 2])  # no division by ~0 for points that are dropped anyway
    uv = proj[:, :2] / depth[:, None]
    uv[behind] = np.nan
    return uv, behind


def image_rect(width: int, height: int) -> Polygon:
    """The image's area in the contract's pixel convention: [-0.5, W - 0.5] x [-0.5, H - 0.5]."""
    return shapely_box(-0.5, -0.5, width - 0.5, height - 0.5)


def in_image(uv: np.ndarray, width: int, height: int) -> np.ndarray:
    """True where a finite pixel coordinate lies inside the image rectangle."""
    uv = np.asarray(uv, dtype=np.float64)
    x, y = uv[..., 0], uv[..., 1]
    # NaN compares False, so corners behind the camera are never in the image.
    return (x >= -0.5) & (x <= width - 0.5) & (y >= -0.5) & (y <= height - 0.5)


def clip_corners_at_near_plane(corners: np.ndarray, near: float = NEAR_PLANE) -> np.ndarray:
    """Vertices of the cuboid cut by the plane z = near, keeping the part in front.

    The cut of a convex polyhedron by a plane is convex and its vertices are the original
    vertices in front plus the points where edges cross the plane, so its silhouette is the
    convex hull of their projections.
    """
    corners = np.asarray(corners, dtype=np.float64)
    z = corners[:, 2]
    keep = [corners[z >= near]]
    for a, b in SKELETON:
        za, zb = z[a], z[b]
        if (za < near) != (zb < near):
            t = (near - za) / (zb - za)
            keep.append((corners[a] + t * (corners[b] - corners[a]))[None])
    return np.concatenate(keep, axis=0)


def silhouette(corners: np.ndarray, K: np.ndarray, near: float = NEAR_PLANE) -> Polygon:
    """The projected cuboid as a polygon (empty when it lies wholly behind the near plane)."""
    clipped = clip_corners_at_near_plane(corners, near)
    if len(clipped) == 0:
        return Polygon()
    uv, _ = project_points(K, clipped, near=near - 1e-9)
    hull = shapely.convex_hull(shapely.multipoints(uv))
    return hull if isinstance(hull, Polygon) else Polygon()


def self_occluded_corners(box: Box3D) -> np.ndarray:
    """(8,) True where the cuboid hides its own corner from a camera at the origin.

    A vertex of a convex solid is visible exactly when at least one face touching it faces the
    camera; a face faces the camera when its outward normal points back towards the origin.
    """
    return self_occluded_corners_batch(box.center, box.dims, box.rotation)[0]


@dataclass(frozen=True)
class BoxProjection:
    """What the contract derives from a cuboid, K and an image size.

    keypoints: (8, 2), NaN for corners behind the camera (outside-image corners keep raw x, y).
    bbox: [x1, y1, x2, y2] of the in-image part of the near-clipped silhouette, or None when
    none of it is in the image. truncation: fraction of the silhouette's area outside the image.
    """

    keypoints: np.ndarray
    in_image: np.ndarray
    behind_camera: np.ndarray
    bbox: np.ndarray | None
    truncation: float


def project_box(box: Box3D, K: np.ndarray, width: int, height: int, near: float = NEAR_PLANE) -> BoxProjection:
    """Project a cuboid and compute its keypoints, flags, bbox and truncation (project_boxes on a batch of one)."""
    return project_boxes(box.corners(), K, width, height, near)[0]


@dataclass(frozen=True)
class BoxProjections:
    """BoxProjection for N cuboids at once, as arrays: row i (self[i]) is box i's BoxProjection.

    keypoints (N, 8, 2), in_image and behind_camera (N, 8), bbox (N, 4) with a row of NaN where
    BoxProjection's bbox is None, truncation (N,).
    """

    keypoints: np.ndarray
    in_image: np.ndarray
    behind_camera: np.ndarray
    bbox: np.ndarray
    truncation: np.ndarray

    def __len__(self) -> int:
        return len(self.truncation)

    def has_bbox(self) -> np.ndarray:
        """(N,) True where some part of the cuboid is in the image (project_box's bbox is not None)."""
        return ~np.isnan(self.bbox[:, 0])

    def __getitem__(self, i: int) -> BoxProjection:
        bbox = None if np.isnan(self.bbox[i, 0]) else self.bbox[i]
        return BoxProjection(self.keypoints[i], self.in_image[i], self.behind_camera[i], bbox, float(self.truncation[i]))


def project_boxes(corners: np.ndarray, K: np.ndarray, width: int, height: int,
                  near: float = NEAR_PLANE) -> BoxProjections:
    """Project N cuboids given as (N, 8, 3) corners (cuboid_corners): keypoints, flags, bbox, truncation.

    project_box is this on a batch of one, so a box's projection is the same alone or in a batch.
    Why arrays: converters project every object of a frame; one object at a time, numpy's per-call
    cost and one shapely call per step dominate. Here the projection (project_points' arithmetic)
    and the common case (every corner in the image, so the convex silhouette is inside the convex
    image and nothing is cut) are whole-array operations, and the silhouettes of the rest go through
    shapely's vectorised functions in one call each. Cuboids with a corner behind the camera (rare)
    are clipped at the near plane one by one (silhouette).
    """
    corners = np.asarray(corners, dtype=np.float64).reshape(-1, 8, 3)
    n = len(corners)
    K = np.asarray(K, dtype=np.float64)
    behind = corners[..., 2] < near
    proj = corners @ K.T  # one 8x3 @ 3x3 product per box, as project_points does
    depth = np.where(behind, 1.0, proj[..., 2])
    uv = proj[..., :2] / depth[..., None]
    uv[behind] = np.nan
    inside = in_image(uv, width, height)
    bbox = np.full((n, 4), np.nan)
    truncation = np.ones(n)
    whole = inside.all(axis=1)
    bbox[whole] = np.concatenate([uv[whole].min(axis=1), uv[whole].max(axis=1)], axis=1)
    truncation[whole] = 0.0
    cut = np.flatnonzero(~whole)
    if len(cut):
        shapes = np.empty(len(cut), dtype=object)
        front = ~behind[cut].any(axis=1)
        if front.any():
            # No corner behind: the near-plane clip keeps all eight, and project_points gives uv again.
            shapes[front] = shapely.convex_hull(shapely.multipoints(uv[cut[front]]))
        for j in np.flatnonzero(~front):
            shapes[j] = silhouette(corners[cut[j]], K, near)
        polygon = shapely.get_type_id(shapes) == shapely.GeometryType.POLYGON  # silhouette's isinstance test
        area = np.where(polygon, shapely.area(shapes), 0.0)
        ok = polygon & ~shapely.is_empty(shapes) & (area > 0)
        if ok.any():
            visible = shapely.intersection(shapes[ok], _cached_image_rect(width, height))
            visible_area = shapely.area(visible)
            seen = ~shapely.is_empty(visible) & (visible_area > 0)
            rows = cut[ok][seen]
            bbox[rows] = shapely.bounds(visible[seen])
            truncation[rows] = np.clip(1.0 - visible_area[seen] / area[ok][seen], 0.0, 1.0)
    return BoxProjections(uv, inside, behind, bbox, truncation)


@functools.lru_cache(maxsize=64)
def _cached_image_rect(width: int, height: int) -> Polygon:
    # The same polygon as image_rect (shapely geometries are immutable); building one costs as
    # much as a frame's intersection, and a dataset has one or a few image sizes.
    return image_rect(width, height)


def self_occluded_corners_batch(centers: np.ndarray, dims: np.ndarray, rotations: np.ndarray) -> np.ndarray:
    """(N, 8) self_occluded_corners of N boxes (one Box3D is a batch of one)."""
    centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
    rotations = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    along = (rotations.transpose(0, 2, 1) @ centers[:, :, None])[:, :, 0]  # centre along each object axis
    half = np.asarray(dims, dtype=np.float64).reshape(-1, 3) / 2.0
    facing_plus = along + half < 0  # face at +half along the axis, outward normal +axis
    facing_minus = -along + half < 0
    # (N, 8, 3): the faces at each corner
    facing = np.where(CORNER_SIGNS[None] > 0, facing_plus[:, None, :], facing_minus[:, None, :])
    return ~facing.any(axis=2)


# ---------------------------------------------------------------------------------------------
# Ground plane and camera pose relative to it
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Plane:
    """n . X + d = 0 in the camera frame, n a unit normal pointing up (away from the ground).

    For a camera above the ground, d is its height above the plane.
    """

    normal: np.ndarray
    offset: float

    def __post_init__(self) -> None:
        n = np.asarray(self.normal, dtype=np.float64).reshape(3)
        norm = np.linalg.norm(n)
        if not np.isfinite(norm) or norm == 0:
            raise ValueError("plane normal must be a finite non-zero vector")
        object.__setattr__(self, "normal", n / norm)
        object.__setattr__(self, "offset", float(self.offset) / norm)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Signed height of points above the plane."""
        return np.asarray(points, dtype=np.float64) @ self.normal + self.offset

    @property
    def camera_height(self) -> float:
        """Height of the camera centre (the origin) above the plane."""
        return self.offset

    @property
    def camera_pitch(self) -> float:
        """Angle of the optical axis below the horizon (radians, positive looking down)."""
        return float(math.asin(np.clip(-self.normal[2], -1.0, 1.0)))

    def tilt(self, up: np.ndarray) -> float:
        """Angle (radians) between the normal and the direction `up` (a unit vector)."""
        return math.acos(float(np.clip(np.dot(self.normal, up), -1.0, 1.0)))


def fit_plane(points: np.ndarray, up_hint: np.ndarray = np.array([0.0, -1.0, 0.0]), iterations: int = 3) -> Plane:
    """Least-squares plane through points, re-fitted with inverse-residual weights (IRLS).

    The normal is oriented along `up_hint`. Needs at least three non-collinear points.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) < 3:
        raise ValueError("a plane needs at least three points")
    weights = np.ones(len(pts))
    for _ in range(max(1, iterations)):
        w = weights / weights.sum()
        mean = (pts * w[:, None]).sum(axis=0)
        centred = (pts - mean) * np.sqrt(w)[:, None]
        _, sing, vt = np.linalg.svd(centred, full_matrices=False)
        normal = vt[-1]
        if sing[1] < 1e-9:
            raise ValueError("points are collinear: no unique plane")
        residual = np.abs((pts - mean) @ normal)
        weights = 1.0 / np.maximum(residual, 0.02)
    if np.dot(normal, up_hint) < 0:
        normal = -normal
    return Plane(normal, -float(np.dot(normal, mean)))


def fit_ground(bottoms: np.ndarray, up: np.ndarray, min_objects: int, max_tilt: float) -> Plane | None:
    """The ground through objects' bottom corners, or None where they do not settle it.

    bottoms: (N, 4, 3), the ground-contact corners (4-7) of N objects in one frame. Fitted with
    fit_plane's reweighted least squares (a few boxes on a kerb or floating barely move it) through
    all 4N points, the normal along `up`. None with fewer than `min_objects` objects, for points
    that fix no unique plane, and for a fit tilted more than `max_tilt` (radians) from `up`. The
    sources' own policy (which objects count, the thresholds, what to use instead) is the
    converters'; this is the fit they share.
    """
    bottoms = np.asarray(bottoms, dtype=np.float64).reshape(-1, 4, 3)
    if len(bottoms) < min_objects:
        return None
    try:
        plane = fit_plane(bottoms.reshape(-1, 3), up_hint=up)
    except ValueError:  # degenerate points: no unique plane
        return None
    return plane if plane.tilt(up) <= max_tilt else None


def plane_from_height_pitch(height: float, pitch: float, roll: float = 0.0) -> Plane:
    """Ground plane seen by a camera `height` metres up, pitched down by `pitch`, rolled by `roll`."""
    up_world_in_cam = rot_z(roll) @ rot_x(pitch) @ np.array([0.0, -1.0, 0.0])
    # Pitch down tilts "up" towards the camera's -z: rot_x(pitch) maps (0,-1,0) -> (0,-cos,-sin).
    return Plane(up_world_in_cam, height)

