"""Mesh primitives and the parts container the asset builders share.

A built asset is a dict role -> mesh ("paint", "glass", "tyre", "skin", ...): one mesh per
material role, so that a backend makes one object with one material slot per role. A mesh is a
`Piece` (bare `vertices` and `faces` arrays, all any consumer reads), not a trimesh.Trimesh: the
raster preview builds every agent in view every frame, and constructing two Trimesh objects per
role (assembly, then the fit) was a third of that. Meshes made with `_mesh` (some static pieces)
and user assets are trimesh objects; consumers read only `vertices` and `faces` either way.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import trimesh

# A hexahedron's 8 corners: bottom quad 0-3 then top quad 4-7, both counter-clockwise from above.
_HEX_FACES = np.array(
    [
        [0, 2, 1], [0, 3, 2],  # bottom (facing down)
        [4, 5, 6], [4, 6, 7],  # top
        [0, 1, 5], [0, 5, 4],
        [1, 2, 6], [1, 6, 5],
        [2, 3, 7], [2, 7, 6],
        [3, 0, 4], [3, 4, 7],
    ],
    dtype=np.int64,
)


def _mesh(vertices: np.ndarray, faces: np.ndarray) -> trimesh.Trimesh:
    return trimesh.Trimesh(vertices=np.asarray(vertices, dtype=np.float64), faces=np.asarray(faces, dtype=np.int64), process=False)


class Piece:
    """A primitive before it joins its role's mesh: bare vertex and face arrays.

    Why not a trimesh: an agent is built from dozens of primitives every frame, and constructing
    (and transforming) a Trimesh per primitive cost most of a frame's re-randomisation. Parts
    concatenates them into one Piece per role.
    """

    __slots__ = ("vertices", "faces")

    def __init__(self, vertices, faces) -> None:
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)


def box(lo, hi) -> Piece:
    """Axis-aligned box between corners lo and hi (in any order: the faces always face out)."""
    (a0, b0, c0), (a1, b1, c1) = (float(c) for c in lo), (float(c) for c in hi)
    x0, x1 = (a0, a1) if a0 <= a1 else (a1, a0)
    y0, y1 = (b0, b1) if b0 <= b1 else (b1, b0)
    z0, z1 = (c0, c1) if c0 <= c1 else (c1, c0)
    quad = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
    return hexahedron(quad, z0, quad, z1)


def hexahedron(bottom, z0: float, top, z1: float) -> Piece:
    """Solid between a bottom quad at z0 and a top quad at z1 (xy corners, counter-clockwise)."""
    v = np.empty((8, 3))
    v[:4, :2], v[:4, 2] = bottom, z0
    v[4:, :2], v[4:, 2] = top, z1
    return Piece(v, _HEX_FACES)


def trapezoid_x(x0b: float, x1b: float, x0t: float, x1t: float, wb: float, wt: float, z0: float, z1: float) -> Piece:
    """Solid symmetric about y = 0: bottom spans x0b..x1b, width wb; top spans x0t..x1t, width wt."""
    return hexahedron(
        [(x0b, -wb / 2), (x1b, -wb / 2), (x1b, wb / 2), (x0b, wb / 2)], z0,
        [(x0t, -wt / 2), (x1t, -wt / 2), (x1t, wt / 2), (x0t, wt / 2)], z1,
    )


def prism_y(profile_xz, y0: float, y1: float) -> Piece:
    """A convex x-z profile (a side view: a car's body, a wheel arch) extruded from y0 to y1.

    Why: a vehicle's silhouette (sloped bonnet, raked nose, upright tail) is a side profile; a
    hexahedron has only four corners. The profile's points may come in either turning order;
    the faces are wound to face outward (the raster backend culls back faces).
    """
    prof = [(float(a), float(b)) for a, b in profile_xz]
    n = len(prof)
    # Shoelace in plain floats (a car has two dozen of these; numpy's per-call overhead dominated).
    area = sum(prof[i - 1][0] * prof[i][1] - prof[i][0] * prof[i - 1][1] for i in range(n))
    if area < 0:  # make the profile counter-clockwise with x right and z up
        prof.reverse()
    pts = np.array(prof)
    ya, yb = (y0, y1) if y0 <= y1 else (y1, y0)
    v = np.empty((2 * n, 3))
    v[:n, 0], v[:n, 1], v[:n, 2] = pts[:, 0], ya, pts[:, 1]
    v[n:, 0], v[n:, 1], v[n:, 2] = pts[:, 0], yb, pts[:, 1]
    return Piece(v, _prism_faces(n))


@lru_cache(maxsize=None)
def _prism_faces(n: int) -> np.ndarray:
    """Faces of `prism_y` for an n-gon: fans on both caps and a quad per edge, outward."""
    # A triangle counter-clockwise in (x right, z up) faces -y (x cross z = -y): the ya cap's fan
    # runs forwards, the yb cap's backwards; a side quad i, j runs ya -> yb on its right.
    k = np.arange(1, n - 1)
    cap_a = np.column_stack([np.zeros(n - 2, dtype=np.int64), k, k + 1])
    cap_b = np.column_stack([np.full(n - 2, n), n + k + 1, n + k])
    i = np.arange(n)
    j = (i + 1) % n
    side = np.concatenate([np.column_stack([i, j + n, j]), np.column_stack([i, i + n, j + n])])
    faces = np.concatenate([cap_a, cap_b, side]).astype(np.int64)
    faces.flags.writeable = False
    return faces


def frustum(center_xy, z0: float, z1: float, r0: float, r1: float, sections: int = 16) -> Piece:
    """A capped cone segment about a vertical axis (a cylinder when r0 == r1)."""
    cos_a, sin_a = _ring(sections)
    cx, cy = center_xy
    v = np.empty((2 * sections + 2, 3))
    v[:sections, 0], v[:sections, 1], v[:sections, 2] = cx + r0 * cos_a, cy + r0 * sin_a, z0
    v[sections:2 * sections, 0], v[sections:2 * sections, 1], v[sections:2 * sections, 2] = cx + r1 * cos_a, cy + r1 * sin_a, z1
    v[2 * sections:] = [[cx, cy, z0], [cx, cy, z1]]
    return Piece(v, _frustum_faces(sections))


@lru_cache(maxsize=None)
def _ring(sections: int) -> tuple[np.ndarray, np.ndarray]:
    """cos and sin of `sections` angles evenly spaced from 0 (frustum's rings)."""
    a = np.linspace(0, 2 * math.pi, sections, endpoint=False)
    c, s = np.cos(a), np.sin(a)
    c.flags.writeable = False
    s.flags.writeable = False
    return c, s


@lru_cache(maxsize=None)
def _frustum_faces(sections: int) -> np.ndarray:
    """The faces of `frustum` (they depend only on the number of sections)."""
    i = np.arange(sections)
    j = (i + 1) % sections
    side = np.concatenate([np.column_stack([i, j, j + sections]), np.column_stack([i, j + sections, i + sections])])
    c0, c1 = 2 * sections, 2 * sections + 1
    caps = np.concatenate([np.column_stack([np.full(sections, c0), j, i]), np.column_stack([np.full(sections, c1), i + sections, j + sections])])
    faces = np.concatenate([side, caps])
    faces.flags.writeable = False
    return faces


def cylinder_between(p0, p1, radius: float, sections: int = 10) -> Piece:
    """A capped cylinder from point p0 to point p1."""
    p0, p1 = np.asarray(p0, dtype=np.float64), np.asarray(p1, dtype=np.float64)
    length = float(np.linalg.norm(p1 - p0))
    m = frustum((0.0, 0.0), 0.0, max(length, 1e-6), radius, radius, sections)
    t = _align_z(p1 - p0, p0)
    return Piece(m.vertices @ t[:3, :3].T + t[:3, 3], m.faces)


def _align_z(direction, origin) -> np.ndarray:
    """4x4 taking +z to `direction` (normalised) and the origin to `origin`."""
    d = np.asarray(direction, dtype=np.float64)
    n = np.linalg.norm(d)
    z = d / n if n > 0 else np.array([0.0, 0.0, 1.0])
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = _cross(helper, z)
    x /= np.linalg.norm(x)
    y = _cross(z, x)
    t = np.eye(4)
    t[:3, 0], t[:3, 1], t[:3, 2], t[:3, 3] = x, y, z, origin
    return t


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """np.cross for two 3-vectors, without its generic-axis overhead (called per primitive)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def wheel(center, radius: float, width: float, sections: int = 16) -> Piece:
    """A disc-like wheel whose axle is the y axis."""
    # cylinder_between(c - (0, w/2, 0), c + (0, w/2, 0), radius) with its frame written out: the
    # axis y, local x -> world z, local y -> world x (what _align_z gives for +y), same vertices.
    c = np.asarray(center, dtype=np.float64)
    cos_a, sin_a = _ring(sections)
    n = sections
    v = np.empty((2 * n + 2, 3))
    v[:n, 0] = v[n:2 * n, 0] = c[0] + radius * sin_a
    v[:n, 2] = v[n:2 * n, 2] = c[2] + radius * cos_a
    v[:n, 1], v[n:2 * n, 1] = c[1] - width / 2, c[1] - width / 2 + width
    v[2 * n:] = [[c[0], c[1] - width / 2, c[2]], [c[0], c[1] - width / 2 + width, c[2]]]
    return Piece(v, _frustum_faces(n))


def ring_y(center, r_in: float, r_out: float, width: float, sections: int = 20) -> Piece:
    """A flat annulus (bicycle tyre) in the x-z plane, axle along y."""
    v, f = _ring_y_at_origin(float(r_in), float(r_out), float(width), int(sections))
    return Piece(v + np.asarray(center, dtype=np.float64), f)


@lru_cache(maxsize=64)
def _ring_y_at_origin(r_in: float, r_out: float, width: float, sections: int) -> tuple[np.ndarray, np.ndarray]:
    """ring_y's mesh at the origin, made once per size: trimesh builds an annulus from scratch (a
    cyclist's four rings were most of its build time) and the wheels of every cyclist are alike."""
    m = trimesh.creation.annulus(r_min=r_in, r_max=r_out, height=width, sections=sections)
    rot = np.eye(4)
    rot[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]  # z axis -> y axis
    m.apply_transform(rot)
    v, f = np.array(m.vertices, dtype=np.float64), np.array(m.faces, dtype=np.int64)
    v.flags.writeable = False
    f.flags.writeable = False
    return v, f


def ellipsoid(center, radii, subdivisions: int = 1) -> Piece:
    v, f = _unit_sphere(subdivisions)
    return Piece(v * np.asarray(radii, dtype=np.float64) + np.asarray(center, dtype=np.float64), f)


@lru_cache(maxsize=None)
def _unit_sphere(subdivisions: int) -> tuple[np.ndarray, np.ndarray]:
    """The unit icosphere's arrays, made once (trimesh builds it from scratch on every call)."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    v, f = np.array(m.vertices, dtype=np.float64), np.array(m.faces, dtype=np.int64)
    v.flags.writeable = False
    f.flags.writeable = False
    return v, f


def quad(p0, p1, p2, p3) -> Piece:
    """A two-triangle quad, corners in counter-clockwise order seen from its front."""
    return Piece(np.array([p0, p1, p2, p3], dtype=np.float64), np.array([[0, 1, 2], [0, 2, 3]]))


class Parts:
    """Meshes grouped by material role; `add` accumulates, `meshes()` concatenates per role."""

    def __init__(self) -> None:
        self._items: dict[str, list[Piece]] = {}

    def add(self, role: str, *meshes: Piece) -> None:
        self._items.setdefault(role, []).extend(meshes)

    def meshes(self) -> dict[str, Piece]:
        out = {}
        for role in sorted(self._items):
            items = self._items[role]
            v, f, n = [], [], 0
            for m in items:
                v.append(m.vertices)
                f.append(m.faces + n)
                n += len(m.vertices)
            out[role] = Piece(np.concatenate(v), np.concatenate(f))
        return out


def bounds_of(meshes: dict) -> np.ndarray:
    """(2, 3) min and max over all parts."""
    v = np.vstack([m.vertices for m in meshes.values()])
    return np.stack([v.min(axis=0), v.max(axis=0)])


def fit_to_dims(meshes: dict, dims) -> tuple[dict[str, Piece], np.ndarray]:
    """Scale each axis and centre so the parts' bounds are exactly the cuboid of `dims`.

    Returns the fitted parts and the raw extents (to check the design was close: builders make
    their geometry from the dims, so the per-axis scale stays within a few percent).
    """
    b = bounds_of(meshes)
    raw = b[1] - b[0]
    scale = np.asarray(dims, dtype=np.float64) / np.maximum(raw, 1e-9)
    mid = (b[0] + b[1]) / 2.0
    out = {}
    for role, m in meshes.items():
        out[role] = Piece((np.asarray(m.vertices) - mid) * scale, m.faces)
    return out, raw
