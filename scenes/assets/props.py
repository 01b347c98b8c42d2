"""Traffic cone (annotated) and the street furniture (not annotated) as parts.

Furniture kinds: street_light, traffic_light, tree (species round, conical, columnar,
spreading), bin, bench, bollard, hydrant, hedge, bush, planter, signpost, bus_shelter, fence,
guardrail; their dims and params are listed in docs/scenes.md.

Furniture is built in its cuboid's frame like an agent (x forward = the direction its arm or
face points), so one fit rule and one transform serve both.
"""

from __future__ import annotations

import math


from omnigen.scenes.assets.parts import Parts, box, cylinder_between, ellipsoid, frustum, hexahedron, trapezoid_x


def traffic_cone(dims, p: dict) -> Parts:
    """A traffic-control device: by p['style'] a cone (square base slab, one or two
    retroreflective stripes), a banded cone (wide bands), a barrel (drum) or a delineator post."""
    style = p.get("style", "cone")
    if style == "barrel":
        return _barrel(dims)
    if style == "delineator":
        return _delineator(dims)
    l, w, h = dims
    parts = Parts()
    base_h = 0.045 * h
    parts.add("cone_base", box((-l / 2, -w / 2, 0.0), (l / 2, w / 2, base_h)))
    r0, r1 = 0.33 * min(l, w), 0.035 * min(l, w) / 0.37
    if style == "banded":
        stripes = [(0.18, 0.36), (0.5, 0.68)]
    else:
        stripes = [(0.55, 0.72)] if int(p.get("stripes", 1)) == 1 else [(0.36, 0.47), (0.6, 0.71)]
    cuts = [0.0] + [c for band in stripes for c in band] + [1.0]
    radius = lambda t: r0 + (r1 - r0) * t  # noqa: E731
    for i in range(len(cuts) - 1):
        role = "cone_stripe" if i % 2 == 1 else "cone"
        z0, z1 = base_h + cuts[i] * (h - base_h), base_h + cuts[i + 1] * (h - base_h)
        parts.add(role, frustum((0.0, 0.0), z0, z1, radius(cuts[i]), radius(cuts[i + 1]), 20))
    return parts


def _barrel(dims) -> Parts:
    """A channelizing drum: a black base ring, orange and white bands, a slightly narrower top."""
    l, w, h = dims
    parts = Parts()
    parts.add("cone_base", frustum((0.0, 0.0), 0.0, 0.06, l / 2, l / 2, 16))
    cuts = [0.06, 0.25, 0.38, 0.52, 0.65, 0.8, 0.93]
    for i in range(len(cuts) - 1):
        z0, z1 = cuts[i] * h / 1.0, cuts[i + 1] * h / 1.0
        r0, r1 = (0.46 - 0.05 * cuts[i]) * l, (0.46 - 0.05 * cuts[i + 1]) * l
        parts.add("cone_stripe" if i % 2 else "cone", frustum((0.0, 0.0), z0, z1, r0, r1, 16))
    parts.add("cone", frustum((0.0, 0.0), 0.93 * h, h, (0.46 - 0.05 * 0.93) * l, 0.36 * l, 16))
    return parts


def _delineator(dims) -> Parts:
    """A post on a heavy base (a channelizer or bollard cone), white reflective bands near the top."""
    l, w, h = dims
    parts = Parts()
    parts.add("cone_base", box((-l / 2, -w / 2, 0.0), (l / 2, w / 2, 0.05)))
    parts.add("cone_base", frustum((0.0, 0.0), 0.05, 0.12, 0.3 * l, 0.15 * l, 12))
    r = 0.12 * l
    cuts = [0.12 / h, 0.6, 0.7, 0.78, 0.88, 1.0]
    for i in range(len(cuts) - 1):
        parts.add("cone_stripe" if i % 2 else "cone", frustum((0.0, 0.0), cuts[i] * h, cuts[i + 1] * h, r, r * (0.9 if i == 4 else 1.0), 12))
    return parts


# ---------------------------------------------------------------------------------------------
# Furniture: ground at z = 0, x from -l/2 to l/2
# ---------------------------------------------------------------------------------------------


def street_light(dims, p: dict) -> Parts:
    l, w, h = dims
    parts = Parts()
    r = float(p.get("pole_radius", 0.09))
    x = -l / 2 + 0.12
    parts.add("metal", frustum((x, 0.0), 0.0, 0.5, r * 1.6, r * 1.6, 12))
    parts.add("metal", frustum((x, 0.0), 0.5, h - 0.1, r, r * 0.7, 12))
    parts.add("metal", cylinder_between((x, 0.0, h - 0.25), (l / 2 - 0.3, 0.0, h - 0.25), 0.05, 8))
    parts.add("metal", box((l / 2 - 0.6, -w / 2, h - 0.4), (l / 2, w / 2, h)))
    parts.add("lamp", box((l / 2 - 0.55, -w / 2 + 0.05, h - 0.43), (l / 2 - 0.05, w / 2 - 0.05, h - 0.4)))
    return parts


def traffic_light(dims, p: dict) -> Parts:
    l, w, h = dims
    parts = Parts()
    r = float(p.get("pole_radius", 0.1))
    x = -l / 2 + 0.12
    arm_z = h - 0.2
    parts.add("metal", frustum((x, 0.0), 0.0, arm_z + 0.2, r, r * 0.8, 12))
    parts.add("metal", cylinder_between((x, 0.0, arm_z), (l / 2 - 0.1, 0.0, arm_z), 0.07, 8))
    # The signal head hangs at the arm's end, facing the approaching traffic (+-y in this frame).
    hx = l / 2 - 0.25
    parts.add("signal", box((hx - 0.2, -w / 2, arm_z - 1.1), (hx + 0.2, w / 2, arm_z)))
    lit = int(p.get("state", 0))
    for k, role in enumerate(("red", "amber", "green")):
        z = arm_z - 0.25 - 0.3 * k
        name = f"lamp_{role}" if k == lit else f"lamp_{role}_off"
        for side in (-1.0, 1.0):
            y0, y1 = sorted((side * w / 2, side * (w / 2 - 0.03)))
            parts.add(name, box((hx - 0.11, y0, z - 0.11), (hx + 0.11, y1, z + 0.11)))
    return parts


TRUNK_DEFAULT = {"round": 2.8, "conical": 1.0, "columnar": 1.5, "spreading": 3.0}


def tree(dims, p: dict) -> Parts:
    """A street tree by p['species']: round (lime, maple), conical (conifer), columnar (poplar,
    hornbeam 'Fastigiata') or spreading (plane tree). The crown fills l x w and tops out at h;
    `trunk_height` is where the crown starts. Lumps on the crown break the ellipsoid's outline."""
    l, w, h = dims
    parts = Parts()
    species = p.get("species", "round")
    trunk = float(p.get("trunk_height", TRUNK_DEFAULT.get(species, 2.8)))
    trunk = min(trunk, 0.7 * h)
    tr = float(p.get("trunk_radius", 0.14))
    rz = (h - trunk) / 2.0
    zc = trunk + rz
    if species == "conical":
        parts.add("bark", frustum((0.0, 0.0), 0.0, trunk + 0.6 * rz, tr, tr * 0.5, 8))
        tiers = 4
        for k in range(tiers):  # stacked cones, each overlapping the one below
            z0 = trunk + k * (h - trunk) / (tiers + 0.6)
            z1 = h if k == tiers - 1 else z0 + 1.6 * (h - trunk) / (tiers + 0.6)
            shrink = 1.0 - 0.2 * k
            parts.add("leaves", _elliptic_frustum(z0, z1, l / 2 * shrink, w / 2 * shrink, 0.02, 12))
        return parts
    parts.add("bark", frustum((0.0, 0.0), 0.0, zc, tr, tr * 0.6, 8))
    if species == "spreading":
        # A flatter core and four limbs out to lumps that make the rim (and reach l/2, w/2).
        parts.add("leaves", ellipsoid((0.0, 0.0, zc), (0.75 * l / 2, 0.75 * w / 2, rz), 1))
        for a in (0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi):
            c = (0.6 * l / 2 * round(math.cos(a)), 0.6 * w / 2 * round(math.sin(a)), zc - 0.15 * rz)
            parts.add("bark", cylinder_between((0.0, 0.0, trunk), c, tr * 0.5, 6))
            parts.add("leaves", ellipsoid(c, (0.4 * l / 2, 0.4 * w / 2, 0.65 * rz), 1))
        return parts
    parts.add("leaves", ellipsoid((0.0, 0.0, zc), (l / 2, w / 2, rz), 1 if species == "columnar" else 2))
    if species == "round":
        for a in (0.8, 2.9, 5.0):
            c = (0.35 * l / 2 * math.cos(a), 0.35 * w / 2 * math.sin(a), zc + 0.25 * rz)
            parts.add("leaves", ellipsoid(c, (0.55 * l / 2, 0.55 * w / 2, 0.6 * rz), 1))
    return parts


def _elliptic_frustum(z0: float, z1: float, rx: float, ry: float, top_ratio: float, sections: int):
    """A frustum with an elliptic section (rx along x, ry along y), tapering to top_ratio."""
    m = frustum((0.0, 0.0), z0, z1, 1.0, top_ratio, sections)
    v = m.vertices.copy()
    v[:, 0] *= rx
    v[:, 1] *= ry
    return type(m)(v, m.faces)


def hedge(dims, p: dict) -> Parts:
    """A row of shrubs along x: clipped (a box with a slightly tapered top) or a lumpy row."""
    l, w, h = dims
    parts = Parts()
    if p.get("clipped", True):
        parts.add("leaves", box((-l / 2, -w / 2, 0.0), (l / 2, w / 2, 0.8 * h)))
        parts.add("leaves", trapezoid_x(-l / 2, l / 2, -l / 2 + 0.05, l / 2 - 0.05, w, w - 0.15, 0.8 * h, h))
        return parts
    n = int(max(1, min(10, round(l / max(0.9 * w, 0.5)))))
    rx = min(l / 2, 0.65 * l / n)
    xs = [0.0] if n == 1 else [-l / 2 + rx + k * (l - 2 * rx) / (n - 1) for k in range(n)]
    for k, x in enumerate(xs):
        hz = h / 2 if k % 2 == 0 else 0.45 * h
        parts.add("leaves", ellipsoid((x, 0.0, hz), (rx, w / 2, hz), 1))
    parts.add("leaves", box((-l / 2 + 0.5 * rx, -0.4 * w, 0.0), (l / 2 - 0.5 * rx, 0.4 * w, 0.7 * h)))
    return parts


def bush(dims, p: dict) -> Parts:
    l, w, h = dims
    parts = Parts()
    parts.add("leaves", ellipsoid((0.0, 0.0, h / 2), (l / 2, w / 2, h / 2), 1))
    parts.add("leaves", ellipsoid((0.2 * l, 0.1 * w, 0.55 * h), (0.3 * l, 0.3 * w, 0.4 * h), 1))
    parts.add("leaves", ellipsoid((-0.15 * l, -0.15 * w, 0.5 * h), (0.3 * l, 0.3 * w, 0.42 * h), 1))
    return parts


def planter(dims, p: dict) -> Parts:
    """A box or round planter (concrete, wood or metal) with soil and a shrub in it."""
    l, w, h = dims
    parts = Parts()
    bh = min(float(p.get("box_height", 0.5)), 0.6 * h)
    role = {"wood": "wood", "metal": "metal"}.get(p.get("material"), "concrete")
    if p.get("shape") == "round":
        parts.add(role, _elliptic_frustum(0.0, bh, 0.42 * l, 0.42 * w, 0.5 / 0.42, 16))
        parts.add("soil", _elliptic_frustum(bh - 0.06, bh - 0.03, 0.46 * l, 0.46 * w, 1.0, 16))
    else:
        parts.add(role, box((-l / 2, -w / 2, 0.0), (l / 2, w / 2, bh)))
        parts.add("soil", box((-l / 2 + 0.05, -w / 2 + 0.05, bh), (l / 2 - 0.05, w / 2 - 0.05, bh + 0.01)))
    rz = (h - bh + 0.1) / 2
    parts.add("leaves", ellipsoid((0.0, 0.0, h - rz), (0.4 * l, 0.4 * w, rz), 1))
    return parts


SIGN_COLORS = {"red": "sign_red", "blue": "sign_blue", "white": "sign_white", "yellow": "sign_yellow"}


def signpost(dims, p: dict) -> Parts:
    """A traffic sign on a pole; the face looks along +x. Shape and colour as in Vienna-convention signs:
    round red ring on white (prohibitory), round blue (mandatory), triangle red-rimmed (warning),
    square (information, priority), rect (direction)."""
    l, w, h = dims
    parts = Parts()
    shape = p.get("shape", "round")
    main = SIGN_COLORS.get(p.get("color"), "sign_red")
    x1 = l / 2
    plate_h = {"triangle": 0.866 * w, "rect": 0.45 * w}.get(shape, w)
    zc = h - plate_h / 2
    parts.add("metal", frustum((-l / 2 + 0.035, 0.0), 0.0, zc, 0.035, 0.035, 8))
    parts.add("metal", box((-l / 2 + 0.03, -0.03, zc - 0.1), (x1 - 0.02, 0.03, zc + 0.1)))  # clamp
    if shape == "round":
        parts.add(main, cylinder_between((x1 - 0.025, 0.0, zc), (x1 - 0.01, 0.0, zc), w / 2, 16))
        parts.add("sign_white", cylinder_between((x1 - 0.02, 0.0, zc), (x1, 0.0, zc), (0.78 if main == "sign_red" else 0.25) * w / 2, 16))
    elif shape == "triangle":
        z0 = h - plate_h
        for role, inset, x0 in ((main, 0.0, x1 - 0.025), ("sign_white", 0.12 * w, x1 - 0.02)):
            xa, xb = x0, (x1 - 0.01 if inset == 0 else x1)
            zb, zt = z0 + inset * 0.5, h - inset
            half = w / 2 - inset
            # A triangular prism: a hexahedron whose top quad shrinks to a 2 mm edge.
            parts.add(role, hexahedron([(xa, -half), (xb, -half), (xb, half), (xa, half)], zb,
                                       [(xa, -0.001), (xb, -0.001), (xb, 0.001), (xa, 0.001)], zt))
    else:
        parts.add(main, box((x1 - 0.025, -w / 2, h - plate_h), (x1 - 0.01, w / 2, h)))
        parts.add("sign_white", box((x1 - 0.02, -0.42 * w, h - 0.9 * plate_h), (x1, 0.42 * w, h - 0.86 * plate_h)))
        parts.add("sign_white", box((x1 - 0.02, -0.42 * w, h - 0.14 * plate_h), (x1, 0.42 * w, h - 0.1 * plate_h)))
    return parts


def bus_shelter(dims, p: dict) -> Parts:
    """Glass back wall and side wings, four posts, a flat roof, a bench; open towards +y (the road)."""
    l, w, h = dims
    parts = Parts()
    for x in (-l / 2 + 0.05, l / 2 - 0.05):
        for y in (-w / 2 + 0.05, w / 2 - 0.1):
            parts.add("metal", box((x - 0.05, y - 0.05, 0.0), (x + 0.05, y + 0.05, h - 0.1)))
    parts.add("glass", box((-l / 2 + 0.1, -w / 2 + 0.03, 0.1), (l / 2 - 0.1, -w / 2 + 0.06, h - 0.2)))
    for x in (-l / 2 + 0.05, l / 2 - 0.05):
        parts.add("glass", box((x - 0.015, -w / 2 + 0.1, 0.1), (x + 0.015, 0.1, h - 0.2)))
    parts.add("metal", box((-l / 2, -w / 2, h - 0.12), (l / 2, w / 2, h)))
    parts.add("wood", box((-l / 2 + 0.4, -w / 2 + 0.08, 0.42), (0.25 * l, -w / 2 + 0.45, 0.47)))
    if p.get("ad_panel", True):
        x0 = 0.25 * l + 0.1
        parts.add("metal", box((x0, -w / 2 + 0.07, 0.2), (l / 2 - 0.15, -w / 2 + 0.2, h - 0.3)))
        parts.add("sign_white", box((x0 + 0.08, -w / 2 + 0.2, 0.3), (l / 2 - 0.23, -w / 2 + 0.21, h - 0.4)))
    return parts


def fence(dims, p: dict) -> Parts:
    """A fence along x: posts every post_spacing with two rails (rail), slats (picket) or a panel."""
    l, w, h = dims
    parts = Parts()
    style = p.get("style", "rail")
    spacing = max(float(p.get("post_spacing", 2.0)), 0.5)
    n = max(1, int(math.ceil(l / spacing)))
    for k in range(n + 1):
        x = -l / 2 + 0.03 + k * (l - 0.06) / n
        parts.add("metal", box((x - 0.03, -w / 2, 0.0), (x + 0.03, w / 2, h)))
    if style == "panel":
        parts.add("wood", box((-l / 2, -w / 2 + 0.01, 0.05), (l / 2, w / 2 - 0.01, h - 0.05)))
        return parts
    role = "wood" if style == "picket" else "metal"
    for z in (0.3 * h, h - 0.12):
        parts.add(role, box((-l / 2, -w / 2 + 0.01, z), (l / 2, w / 2 - 0.01, z + 0.06)))
    if style == "picket":
        m = min(80, int(l / 0.15))
        for k in range(m):
            x = -l / 2 + (k + 0.5) * l / m
            parts.add("wood", box((x - 0.04, -w / 4, 0.08), (x + 0.04, w / 4, h - 0.02)))
    return parts


def guardrail(dims, p: dict) -> Parts:
    """A steel W-beam guard rail on posts; the beam faces +y (the road)."""
    l, w, h = dims
    parts = Parts()
    spacing = max(float(p.get("post_spacing", 2.0)), 0.5)
    n = max(1, int(math.ceil(l / spacing)))
    for k in range(n + 1):
        x = -l / 2 + 0.4 + k * (l - 0.8) / n if l > 1.0 else 0.0
        parts.add("metal", box((x - 0.05, -w / 2, 0.0), (x + 0.05, -w / 2 + 0.12, h - 0.05)))
        parts.add("metal", box((x - 0.04, -w / 2 + 0.12, h - 0.3), (x + 0.04, w / 2 - 0.06, h - 0.08)))
    parts.add("metal", box((-l / 2, w / 2 - 0.06, h - 0.33), (l / 2, w / 2 - 0.01, h - 0.2)))
    parts.add("metal", box((-l / 2, w / 2 - 0.05, h - 0.2), (l / 2, w / 2, h)))
    return parts


def bin_(dims, p: dict) -> Parts:
    l, w, h = dims
    parts = Parts()
    parts.add("plastic", frustum((0.0, 0.0), 0.0, h - 0.05, 0.42 * l, 0.5 * l, 14))
    parts.add("metal", frustum((0.0, 0.0), h - 0.05, h, 0.5 * l, 0.46 * l, 14))
    return parts


def bench(dims, p: dict) -> Parts:
    """Seat and backrest along x (the bench's length); it faces +y in its own frame."""
    l, w, h = dims
    parts = Parts()
    for x in (-l / 2 + 0.15, l / 2 - 0.15):
        parts.add("metal", box((x - 0.04, -w / 2, 0.0), (x + 0.04, w / 2 - 0.1, 0.45)))
        parts.add("metal", box((x - 0.04, -w / 2, 0.0), (x + 0.04, -w / 2 + 0.06, h)))
    for i in range(3):
        y = -w / 2 + 0.1 + i * 0.15
        parts.add("wood", box((-l / 2, y, 0.42), (l / 2, y + 0.12, 0.46)))
    for i in range(2):
        z = 0.6 + i * 0.13
        parts.add("wood", box((-l / 2, -w / 2 + 0.02, z), (l / 2, -w / 2 + 0.07, z + 0.1)))
    return parts


def bollard(dims, p: dict) -> Parts:
    l, w, h = dims
    parts = Parts()
    if p.get("style") == "dome":
        r = l / 2
        parts.add("metal", frustum((0.0, 0.0), 0.0, h - r, r, r, 12))
        parts.add("metal", ellipsoid((0.0, 0.0, h - r), (r, w / 2, r), 1))
        parts.add("paint_band", frustum((0.0, 0.0), h - r - 0.12, h - r - 0.04, r * 1.0, r * 1.0, 12))
        return parts
    parts.add("metal", frustum((0.0, 0.0), 0.0, h - 0.06, l / 2 * 0.9, l / 2, 12))
    parts.add("paint_band", frustum((0.0, 0.0), h - 0.06, h, l / 2, l / 2 * 0.6, 12))
    return parts


def hydrant(dims, p: dict) -> Parts:
    l, w, h = dims
    parts = Parts()
    r = 0.3 * l
    parts.add("hydrant", frustum((0.0, 0.0), 0.0, h - 0.1, r, r, 12))
    parts.add("hydrant", ellipsoid((0.0, 0.0, h - 0.1), (r, r, 0.1), 1))
    parts.add("hydrant", cylinder_between((-l / 2, 0.0, 0.5 * h), (l / 2, 0.0, 0.5 * h), 0.05, 8))
    parts.add("hydrant", cylinder_between((0.0, -w / 2, 0.55 * h), (0.0, w / 2, 0.55 * h), 0.04, 8))
    return parts


FURNITURE_BUILDERS = {
    "street_light": street_light,
    "traffic_light": traffic_light,
    "tree": tree,
    "bin": bin_,
    "bench": bench,
    "bollard": bollard,
    "hydrant": hydrant,
    "hedge": hedge,
    "bush": bush,
    "planter": planter,
    "signpost": signpost,
    "bus_shelter": bus_shelter,
    "fence": fence,
    "guardrail": guardrail,
}
