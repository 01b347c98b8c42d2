"""Mesh primitives and the parts container the asset builders share.

A built asset is a dict role -> trimesh.Trimesh ("paint", "glass", "tyre", "skin", ...): one mesh
per material role, so that a backend makes one object with one material slot per role. Meshes
are made with process=False: trimesh's vertex merging costs time and changes nothing we draw.
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
    makes one Trimesh per role from these.
    """

    __slots__ = ("vertices", "faces")

    def __init__(self, vertices, faces) -> None:
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)


def box(lo, hi) -> Piece:
    """Axis-aligned box between corners lo and hi."""
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    return hexahedron(
        [(lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1])], lo[2],
        [(lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1])], hi[2],
    )


def hexahedron(bottom, z0: float, top, z1: float) -> Piece:
    """Solid between a bottom quad at z0 and a top quad at z1 (xy corners, counter-clockwise)."""
    b = np.asarray(bottom, dtype=np.float64)
    t = np.asarray(top, dtype=np.float64)
    v = np.vstack([np.column_stack([b, np.full(4, z0)]), np.column_stack([t, np.full(4, z1)])])
    return Piece(v, _HEX_FACES)


def trapezoid_x(x0b: float, x1b: float, x0t: float, x1t: float, wb: float, wt: float, z0: float, z1: float) -> Piece:
    """Solid symmetric about y = 0: bottom spans x0b..x1b, width wb; top spans x0t..x1t, width wt."""
    return hexahedron(
        [(x0b, -wb / 2), (x1b, -wb / 2), (x1b, wb / 2), (x0b, wb / 2)], z0,
        [(x0t, -wt / 2), (x1t, -wt / 2), (x1t, wt / 2), (x0t, wt / 2)], z1,
    )


def frustum(center_xy, z0: float, z1: float, r0: float, r1: float, sections: int = 16) -> Piece:
    """A capped cone segment about a vertical axis (a cylinder when r0 == r1)."""
    a = np.linspace(0, 2 * math.pi, sections, endpoint=False)
    cx, cy = center_xy
    ring0 = np.column_stack([cx + r0 * np.cos(a), cy + r0 * np.sin(a), np.full(sections, z0)])
    ring1 = np.column_stack([cx + r1 * np.cos(a), cy + r1 * np.sin(a), np.full(sections, z1)])
    v = np.vstack([ring0, ring1, [[cx, cy, z0], [cx, cy, z1]]])
    return Piece(v, _frustum_faces(sections))


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
    c = np.asarray(center, dtype=np.float64)
    return cylinder_between(c - [0, width / 2, 0], c + [0, width / 2, 0], radius, sections)


def ring_y(center, r_in: float, r_out: float, width: float, sections: int = 20) -> Piece:
    """A flat annulus (bicycle tyre) in the x-z plane, axle along y."""
    m = trimesh.creation.annulus(r_min=r_in, r_max=r_out, height=width, sections=sections)
    rot = np.eye(4)
    rot[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]  # z axis -> y axis
    m.apply_transform(rot)
    m.apply_translation(center)
    return Piece(m.vertices, m.faces)


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
        self._items: dict[str, list[trimesh.Trimesh]] = {}

    def add(self, role: str, *meshes: trimesh.Trimesh) -> None:
        self._items.setdefault(role, []).extend(meshes)

    def meshes(self) -> dict[str, trimesh.Trimesh]:
        out = {}
        for role in sorted(self._items):
            items = self._items[role]
            v, f, n = [], [], 0
            for m in items:
                v.append(np.asarray(m.vertices))
                f.append(np.asarray(m.faces) + n)
                n += len(m.vertices)
            out[role] = _mesh(np.vstack(v), np.vstack(f))
        return out


def bounds_of(meshes: dict[str, trimesh.Trimesh]) -> np.ndarray:
    """(2, 3) min and max over all parts."""
    v = np.vstack([m.vertices for m in meshes.values()])
    return np.stack([v.min(axis=0), v.max(axis=0)])


def fit_to_dims(meshes: dict[str, trimesh.Trimesh], dims) -> tuple[dict[str, trimesh.Trimesh], np.ndarray]:
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
        out[role] = _mesh((np.asarray(m.vertices) - mid) * scale, m.faces)
    return out, raw
