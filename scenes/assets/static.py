"""The city's static geometry (world coordinates): ground, roads, markings, sidewalks, buildings.

Heights: roads' top at z = 0, paint 1 cm above it (enough for a 24-bit depth buffer with the
raster backend's near plane at 0.25 m out to a few hundred metres), sidewalks and lots at the
kerb height, the ground plane 5 cm below the roads out to 2 km so no camera sees a void.

Windows are real geometry (a frame quad and a glass quad standing 1 and 2 cm proud of the wall),
on every exterior wall except party walls, in rows by floor; ground floors of tall buildings get
shopfront windows. Which windows light up at night is drawn from the facade's own seed, so it is
part of the description and the same in both backends.
"""

from __future__ import annotations

import math

import numpy as np
import trimesh
from shapely.geometry import LineString, Polygon

from omnigen.scenes.assets.parts import _HEX_FACES, Parts, Piece, _mesh, box, hexahedron, quad
from omnigen.scenes.description import Building, City
from omnigen.scenes.shapes import Occupancy, rect_corners

MARKING_Z = 0.01
GROUND_HALF = 2000.0


def triangulate(poly: np.ndarray) -> np.ndarray:
    """Ear clipping of a simple counter-clockwise polygon (n, 2) -> (n - 2, 3) indices."""
    idx = list(range(len(poly)))
    tris = []

    def cross(o, a, b) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    guard = 0
    while len(idx) > 3 and guard < 10000:
        guard += 1
        n = len(idx)
        for k in range(n):
            i0, i1, i2 = idx[k - 1], idx[k], idx[(k + 1) % n]
            a, b, c = poly[i0], poly[i1], poly[i2]
            if cross(a, b, c) <= 1e-12:
                continue  # reflex or degenerate corner
            if any(cross(a, b, poly[j]) >= 0 and cross(b, c, poly[j]) >= 0 and cross(c, a, poly[j]) >= 0
                   for j in idx if j not in (i0, i1, i2)):
                continue
            tris.append((i0, i1, i2))
            idx.pop(k)
            break
        else:
            break  # no ear: give up on the rest (never happens for our simple footprints)
    if len(idx) == 3:
        tris.append(tuple(idx))
    return np.array(tris, dtype=np.int64)


def flat_polygon(poly: np.ndarray, z: float) -> trimesh.Trimesh:
    v = np.column_stack([poly, np.full(len(poly), z)])
    return _mesh(v, triangulate(poly))


def prism(poly: np.ndarray, z0: float, z1: float, cap: bool = True) -> tuple[trimesh.Trimesh, trimesh.Trimesh | None]:
    """Walls of a counter-clockwise footprint extruded from z0 to z1, and the top cap."""
    n = len(poly)
    walls = []
    for i in range(n):
        a, b = poly[i], poly[(i + 1) % n]
        walls.append(quad((a[0], a[1], z0), (b[0], b[1], z0), (b[0], b[1], z1), (a[0], a[1], z1)))
    v = np.vstack([w.vertices for w in walls])
    f = np.vstack([w.faces + 4 * k for k, w in enumerate(walls)])
    return _mesh(v, f), (flat_polygon(poly, z1) if cap else None)


def oriented_box(center, length: float, width: float, yaw: float, z0: float, z1: float) -> trimesh.Trimesh:
    from omnigen.scenes.assets.parts import hexahedron

    c = rect_corners(center, length, width, yaw)
    return hexahedron(c, z0, c, z1)


def flat_rect(center, length: float, width: float, yaw: float, z: float) -> trimesh.Trimesh:
    c = rect_corners(center, length, width, yaw)
    return quad(*[(p[0], p[1], z) for p in c])


# ---------------------------------------------------------------------------------------------


def ground_parts(city: City) -> Parts:
    parts = Parts()
    g = GROUND_HALF
    parts.add("ground", quad((-g, -g, -0.05), (g, -g, -0.05), (g, g, -0.05), (-g, g, -0.05)))
    # Roads cut at the intersections, and each intersection square once: coplanar overlapping
    # faces would shadow each other in a path tracer (a shadow ray leaving one hits the other).
    for road in city.roads:
        axis = 0 if road.axis == "x" else 1
        across = road.start[1 - axis]
        lo, hi = sorted((road.start[axis], road.end[axis]))
        cuts = sorted((i.center[axis] - i.size[axis] / 2, i.center[axis] + i.size[axis] / 2)
                      for i in city.intersections if abs(i.center[1 - axis] - across) < 1e-6)
        cursor = lo
        for a, b in cuts + [(hi, hi)]:
            if a > cursor + 1e-6:
                mid = (cursor + a) / 2
                center = (mid, across) if axis == 0 else (across, mid)
                size = (a - cursor, road.width) if axis == 0 else (road.width, a - cursor)
                parts.add("road", box((center[0] - size[0] / 2, center[1] - size[1] / 2, -0.2), (center[0] + size[0] / 2, center[1] + size[1] / 2, 0.0)))
            cursor = max(cursor, b)
    for i in city.intersections:
        parts.add("road", box((i.center[0] - i.size[0] / 2, i.center[1] - i.size[1] / 2, -0.2), (i.center[0] + i.size[0] / 2, i.center[1] + i.size[1] / 2, 0.0)))
    for s in city.sidewalks:
        role = "lawn" if s.kind == "lawn" else "sidewalk"
        parts.add(role, oriented_box(s.center, s.length, s.width, s.yaw, -0.2, s.height))
    return parts


def marking_parts(city: City) -> Parts:
    parts = Parts()
    for m in city.markings:
        parts.add(f"marking_{m.color}", flat_rect(m.center, m.length, m.width, m.yaw, MARKING_Z))
    for c in city.crosswalks:
        # Bars parallel to the traffic, repeated across the road (along the walking direction).
        pitch = c.stripe_width + c.stripe_gap
        n = int((c.length - 0.4) // pitch)
        start = -(n * pitch - c.stripe_gap) / 2.0 + c.stripe_width / 2.0
        for k in range(n):
            t = start + k * pitch
            center = (c.center[0] + t * math.cos(c.yaw), c.center[1] + t * math.sin(c.yaw))
            parts.add("marking_white", flat_rect(center, c.stripe_width, c.width, c.yaw, MARKING_Z))
    return parts


def building_parts(b: Building, neighbours: Occupancy | None = None) -> Parts:
    """`neighbours`: footprints of all buildings, owned by building_id (see footprints())."""
    """Walls, roof, windows (lit or not) and frames of one building."""
    parts = Parts()
    f = b.facade
    rng = np.random.default_rng(f.seed)
    for part in b.parts:
        poly = np.asarray(part.footprint, dtype=np.float64)
        walls, cap = prism(poly, part.base_z, part.top_z, cap=part.roof == "flat")
        parts.add("wall", walls)
        if cap is not None:
            parts.add("roof", cap)
        else:
            _gable(parts, poly, part.top_z, part.roof_height)
        n = len(poly)
        for i in range(n):
            a, b_ = poly[i], poly[(i + 1) % n]
            if neighbours is not None and _party_wall(a, b_, neighbours, b.building_id):
                continue
            shops = part.base_z < 1.0 and part.top_z - part.base_z > 12.0
            street = shops and not _faces_building(a, b_, neighbours, b.building_id)
            _windows(parts, rng, a, b_, part.base_z, part.top_z, f, ground_floor=shops,
                     awnings=(neighbours, b.building_id) if street else None)
    return parts


def _party_wall(a, b, neighbours: Occupancy, owner: str) -> bool:
    """True when another building stands within 1.5 m outside this wall's middle."""
    d = np.asarray(b) - np.asarray(a)
    length = float(np.hypot(*d))
    if length < 1e-6:
        return True
    normal = np.array([d[1], -d[0]]) / length  # outward for a counter-clockwise footprint
    mid = (np.asarray(a) + np.asarray(b)) / 2.0
    probe = LineString([mid + normal * 0.2, mid + normal * 1.5])
    return neighbours.collides(probe.buffer(0.05), 0.0, ignore_owner=owner)


def _faces_building(a, b, neighbours: Occupancy | None, owner: str) -> bool:
    """True when another building stands within AWNING_ROOM metres in front of this wall's
    middle (a gap between neighbours, not a street or plaza: no awning reaches into it)."""
    if neighbours is None:
        return False
    d = np.asarray(b) - np.asarray(a)
    normal = np.array([d[1], -d[0]]) / max(float(np.hypot(*d)), 1e-9)
    mid = (np.asarray(a) + np.asarray(b)) / 2.0
    probe = LineString([mid + normal * 0.2, mid + normal * AWNING_ROOM])
    return neighbours.collides(probe.buffer(0.05), 0.0, ignore_owner=owner)


def _windows(parts: Parts, rng: np.random.Generator, a, b, z0: float, z1: float, f, ground_floor: bool,
             awnings: tuple | None = None) -> None:
    """`awnings`: (the city's building footprints, this building's id) where the wall's shops may
    put out awnings (a street or plaza in front), else None."""
    d = np.asarray(b, dtype=np.float64) - np.asarray(a, dtype=np.float64)
    length = float(np.hypot(*d))
    u = d / max(length, 1e-9)
    normal = np.array([u[1], -u[0]])
    n_cols = int((length - 1.0) // f.window_spacing)
    floors = int(round((z1 - z0) / f.floor_height))
    if n_cols < 1 or floors < 1:
        return
    margin = (length - n_cols * f.window_spacing) / 2.0
    for k in range(floors):
        base = z0 + k * f.floor_height
        if ground_floor and k == 0:
            if z0 + f.floor_height < z1 - 0.2:
                _shopfronts(parts, rng, a, u, normal, margin, n_cols, z0, f, awnings)
            continue
        else:
            wh, ww, zb = f.window_height, f.window_width, base + 0.5 * (f.floor_height - f.window_height) + 0.15
        if zb + wh > z1 - 0.2:
            continue
        for c in range(n_cols):
            t = margin + (c + 0.5) * f.window_spacing
            center = np.asarray(a) + u * t
            lit = bool(rng.random() < f.lit_fraction)
            for role, off, grow in (("frame", 0.01, 0.08), ("window_lit" if lit else "window", 0.02, 0.0)):
                p = center + normal * off
                h0, h1 = zb - grow, zb + wh + grow
                w2 = ww / 2 + grow
                pa, pb = p - u * w2, p + u * w2
                parts.add(role, quad((pa[0], pa[1], h0), (pb[0], pb[1], h0), (pb[0], pb[1], h1), (pa[0], pa[1], h1)))


# Shopfronts: the ground floor of a tall downtown building is shops, not more of the storeys above.
# Their glazing is near the whole frontage between narrow piers, down to a stallriser (or the
# floor, at a shop's door), set in a surround of its own (cladding, painted or dark stone: the
# "shopfront" role, materials.shopfront_material), and some shops put out an awning. In daylight
# a shop seen from the street is dark: its interior is lit a tenth as brightly as the street, the
# glass mirrors mostly the street below the opposite roofline, and an awning shades the glazing
# and the footway in front. Awnings clear people on the footway (their lowest edge stands at
# least AWNING_CLEARANCE above it) and only walls with AWNING_ROOM free in front get them.
STALLRISER = 0.45  # metres of the surround under a shop window
SHOP_GLASS_TOP = 0.78  # of the storey's height: the glazing's top; the fascia (the sign band) above
SHOP_BAYS = (2, 4)  # bays (window columns) a shop takes, inclusive
AWNING_PROBABILITY = 0.4  # of the shops on a street wall
AWNING_DEPTH = (1.1, 1.6)  # metres out from the wall
AWNING_DROP = 0.45  # metres its outer edge hangs below where it meets the wall
AWNING_VALANCE = 0.22  # the hanging front strip
AWNING_CLEARANCE = 2.3  # metres from the footway to the valance's lower edge, at least
AWNING_ROOM = 2.5  # metres free in front of a wall for it to get awnings
AWNING_SPAWN = 0x5A0  # the shops' own stream beside the facade's seed: the windows' lit draws stay as they were


def _shopfronts(parts: Parts, rng: np.random.Generator, a, u, normal, margin: float, n_cols: int, z0: float, f,
                awnings: tuple | None) -> None:
    """One wall's ground floor as shops: the surround over the storey, each bay's glazing in its
    frame (a shop's first or last bay its door, glazed to the floor), awnings over some shops
    (`awnings` as _windows'; none that would reach within 0.1 m of another building).
    Draws one number a bay from `rng` (lit at night), as the storeys' windows do."""
    fh, sp = f.floor_height, f.window_spacing
    a = np.asarray(a, dtype=np.float64)
    shop_rng = np.random.default_rng([int(f.seed), AWNING_SPAWN, int(round(a[0] * 100.0)) & 0xFFFFFF, int(round(a[1] * 100.0)) & 0xFFFFFF])
    lo, hi = a + u * (margin * 0.5), a + u * (1.5 * margin + n_cols * sp)  # the wall less half its end margins
    s0, s1 = lo + normal * 0.005, hi + normal * 0.005
    parts.add("shopfront", quad((s0[0], s0[1], z0), (s1[0], s1[1], z0), (s1[0], s1[1], z0 + fh), (s0[0], s0[1], z0 + fh)))
    top = z0 + SHOP_GLASS_TOP * fh
    c = 0
    while c < n_cols:
        bays = min(int(shop_rng.integers(SHOP_BAYS[0], SHOP_BAYS[1] + 1)), n_cols - c)
        door = c if shop_rng.random() < 0.5 else c + bays - 1
        awning = awnings is not None and shop_rng.random() < AWNING_PROBABILITY
        depth = float(shop_rng.uniform(*AWNING_DEPTH))
        for col in range(c, c + bays):
            center = a + u * (margin + (col + 0.5) * sp)
            lit = bool(rng.random() < f.lit_fraction)
            zb = z0 + (0.03 if col == door else STALLRISER)
            w2 = 0.46 * sp if col != door else 0.3 * sp
            for role, off, grow in (("frame", 0.01, 0.06), ("window_lit" if lit else "window", 0.02, 0.0)):
                q = center + normal * off
                pa, pb = q - u * (w2 + grow), q + u * (w2 + grow)
                h0, h1 = max(zb - grow, z0 + 0.01), top + grow
                parts.add(role, quad((pa[0], pa[1], h0), (pb[0], pb[1], h0), (pb[0], pb[1], h1), (pa[0], pa[1], h1)))
        if awning:
            z_wall = max(top + 0.5 * (z0 + fh - top), z0 + AWNING_CLEARANCE + AWNING_DROP + AWNING_VALANCE)
            left, right = a + u * (margin + c * sp + 0.1), a + u * (margin + (c + bays) * sp - 0.1)
            reach = Polygon([left + normal * 0.05, right + normal * 0.05, right + normal * (depth + 0.05), left + normal * (depth + 0.05)])
            neighbours, owner = awnings
            if neighbours is None or not neighbours.collides(reach, 0.1, ignore_owner=owner):
                _awning(parts, left, right, normal, z_wall, depth)
        c += bays


def _awning(parts: Parts, left, right, normal, z_wall: float, depth: float) -> None:
    """A fabric awning from the wall (left to right along it, at z_wall) sloping down and out
    `depth` metres, 4 cm thick, with its valance hanging from the outer edge."""
    t = 0.04
    w0, w1 = left + normal * 0.03, right + normal * 0.03
    o0, o1 = w0 + normal * depth, w1 + normal * depth
    z_out = z_wall - AWNING_DROP
    # corners counter-clockwise from above: outer left, outer right, wall right, wall left
    xy = np.array([o0, o1, w1, w0])
    zs = np.array([z_out, z_out, z_wall, z_wall])
    v = np.empty((8, 3))
    v[:4, :2], v[:4, 2] = xy, zs - t
    v[4:, :2], v[4:, 2] = xy, zs
    parts.add("awning", Piece(v, _HEX_FACES))
    inner0, inner1 = o0 - normal * 0.03, o1 - normal * 0.03
    foot = np.array([o0, o1, inner1, inner0])
    parts.add("awning", hexahedron(foot, z_out - AWNING_VALANCE, foot, z_out - t))


def _gable(parts: Parts, poly: np.ndarray, eave: float, rise: float) -> None:
    """A gable roof on a rectangle: ridge along the long side, triangles closing the ends."""
    p0, p1, p2, p3 = poly[:4]
    if np.linalg.norm(p1 - p0) < np.linalg.norm(p2 - p1):
        p0, p1, p2, p3 = p1, p2, p3, p0  # make p0-p1 a long side
    m03, m12 = (p0 + p3) / 2.0, (p1 + p2) / 2.0  # the ridge runs from m03 to m12
    top = eave + rise
    e = lambda p, z: (p[0], p[1], z)  # noqa: E731
    parts.add("roof", quad(e(p0, eave), e(p1, eave), e(m12, top), e(m03, top)))
    parts.add("roof", quad(e(p2, eave), e(p3, eave), e(m03, top), e(m12, top)))
    parts.add("wall", _mesh(np.array([e(p1, eave), e(p2, eave), e(m12, top)]), np.array([[0, 1, 2]])))
    parts.add("wall", _mesh(np.array([e(p3, eave), e(p0, eave), e(m03, top)]), np.array([[0, 1, 2]])))


def footprints(city: City) -> Occupancy:
    """Every building part's footprint, owned by its building's id."""
    occ = Occupancy()
    for b in city.buildings:
        for part in b.parts:
            occ.add(Polygon(part.footprint), b.building_id)
    return occ

