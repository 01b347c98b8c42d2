"""Small 2D helpers shared by layout and placement: oriented rectangles and their polygons."""

from __future__ import annotations

import math

import numpy as np
import shapely
from shapely.geometry import Polygon


def rect_corners(center: tuple[float, float], length: float, width: float, yaw: float) -> np.ndarray:
    """(4, 2) corners, counter-clockwise, of a rectangle `length` along `yaw`, `width` across."""
    c, s = math.cos(yaw), math.sin(yaw)
    hl, hw = length / 2.0, width / 2.0
    local = np.array([[hl, -hw], [hl, hw], [-hl, hw], [-hl, -hw]])
    rot = np.array([[c, -s], [s, c]])
    return local @ rot.T + np.asarray(center, dtype=np.float64)


def rect_polygon(center: tuple[float, float], length: float, width: float, yaw: float) -> Polygon:
    return Polygon(rect_corners(center, length, width, yaw))


def to_world(origin: tuple[float, float], yaw: float, along: float, across: float) -> tuple[float, float]:
    """The point `along` the direction `yaw` and `across` to its left, from `origin`."""
    c, s = math.cos(yaw), math.sin(yaw)
    return (origin[0] + along * c - across * s, origin[1] + along * s + across * c)


def polygon_tuple(poly: Polygon | np.ndarray) -> tuple[tuple[float, float], ...]:
    """Counter-clockwise exterior without the repeated closing point, as plain tuples."""
    if isinstance(poly, Polygon):
        from shapely.geometry.polygon import orient

        pts = np.asarray(orient(poly, 1.0).exterior.coords)[:-1]
    else:
        pts = np.asarray(poly)
    return tuple((float(x), float(y)) for x, y in pts)


class Occupancy:
    """Polygons already placed, with a bounding-box prefilter so each query stays cheap.

    Why not an STRtree for single queries: shapely's tree is immutable and placement inserts one
    shape at a time; a numpy box test followed by exact shapely tests on the few candidates is fast
    enough for the hundreds of shapes a city block holds. The vectorised `collides_many` does query
    a tree: `freeze` builds one over the polygons held so far (a city's static obstacles, once per
    city), copies share it, and only polygons added after it get a tree of their own per query.
    """

    def __init__(self) -> None:
        self.polygons: list[Polygon] = []
        self.owners: list[object] = []
        self._bounds = np.zeros((64, 4))
        self._tree: shapely.STRtree | None = None  # over polygons[:_frozen] (freeze); they never change
        self._frozen = 0

    def add(self, poly: Polygon, owner: object = None, bounds: tuple[float, float, float, float] | None = None) -> None:
        """Store `poly`; `bounds`, when the caller has them, must be poly.bounds (saves asking again)."""
        n = len(self.polygons)
        if n == len(self._bounds):
            self._bounds = np.vstack([self._bounds, np.zeros_like(self._bounds)])
        self._bounds[n] = poly.bounds if bounds is None else bounds
        self.polygons.append(poly)
        self.owners.append(owner)

    def copy(self) -> Occupancy:
        """An independent Occupancy holding the same polygons (shapely geometries are immutable,
        so they are shared): a frame adds to a copy of the city's obstacles, not to them."""
        out = Occupancy()
        out.polygons, out.owners, out._bounds = list(self.polygons), list(self.owners), self._bounds.copy()
        out._tree, out._frozen = self._tree, self._frozen  # the frozen polygons are the copy's first ones too
        return out

    def freeze(self) -> None:
        """Build `collides_many`'s tree over the polygons held now and keep it (for a set queried
        many times: a city's obstacles, which every frame's copy shares). Polygons added later are
        still found, through a tree built per query over them alone."""
        self._tree = shapely.STRtree(self.polygons) if self.polygons else None
        self._frozen = len(self.polygons)

    def collides(self, poly, margin: float = 0.0, ignore_owner: object = None,
                 bounds: tuple[float, float, float, float] | None = None) -> bool:
        """True if `poly` grown by `margin` touches any stored polygon (not those of `ignore_owner`);
        `bounds`, when the caller has them, must be poly.bounds."""
        if not self.polygons:
            return False
        x0, y0, x1, y1 = poly.bounds if bounds is None else bounds
        b = self._bounds[: len(self.polygons)]
        near = np.nonzero((b[:, 0] <= x1 + margin) & (b[:, 2] >= x0 - margin) & (b[:, 1] <= y1 + margin) & (b[:, 3] >= y0 - margin))[0]
        if ignore_owner is not None:
            near = [i for i in near if self.owners[i] != ignore_owner]
        if len(near) == 0:
            return False
        grown = poly.buffer(margin, join_style=2) if margin > 0 else poly
        return any(grown.intersects(self.polygons[i]) for i in near)

    def collides_many(self, polys: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """`collides` for an array of polygons in one vectorised query (a kerb's row of parked
        vehicles at once): True where a polygon grown by `margin` touches a stored one."""
        hit = np.zeros(len(polys), dtype=bool)
        if not self.polygons or not len(polys):
            return hit
        grown = shapely.buffer(polys, margin, join_style="mitre") if margin > 0 else polys
        # The same pairs as one tree over all polygons: `intersects` is tested exactly either way.
        if self._tree is not None:
            cand, _ = self._tree.query(grown, predicate="intersects")
            hit[cand] = True
        if len(self.polygons) > self._frozen:
            cand, _ = shapely.STRtree(self.polygons[self._frozen:]).query(grown, predicate="intersects")
            hit[cand] = True
        return hit
