"""Traffic cone (annotated) and the street furniture (not annotated) as parts.

Furniture is built in its cuboid's frame like an agent (x forward = the direction its arm or
face points), so one fit rule and one transform serve both.
"""

from __future__ import annotations

import math

import numpy as np

from scenes.assets.parts import Parts, box, cylinder_between, ellipsoid, frustum


def traffic_cone(dims, p: dict) -> Parts:
    """A square base slab and a banded cone with one or two retroreflective stripes."""
    l, w, h = dims
    parts = Parts()
    base_h = 0.045 * h
    parts.add("cone_base", box((-l / 2, -w / 2, 0.0), (l / 2, w / 2, base_h)))
    r0, r1 = 0.33 * min(l, w), 0.035 * min(l, w) / 0.37
    stripes = [(0.55, 0.72)] if int(p.get("stripes", 1)) == 1 else [(0.36, 0.47), (0.6, 0.71)]
    cuts = [0.0] + [c for band in stripes for c in band] + [1.0]
    radius = lambda t: r0 + (r1 - r0) * t  # noqa: E731
    for i in range(len(cuts) - 1):
        role = "cone_stripe" if i % 2 == 1 else "cone"
        z0, z1 = base_h + cuts[i] * (h - base_h), base_h + cuts[i + 1] * (h - base_h)
        parts.add(role, frustum((0.0, 0.0), z0, z1, radius(cuts[i]), radius(cuts[i + 1]), 20))
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


def tree(dims, p: dict) -> Parts:
    l, w, h = dims
    parts = Parts()
    trunk = float(p.get("trunk_height", 2.8))
    tr = float(p.get("trunk_radius", 0.14))
    crown_top = h
    rz = (crown_top - trunk) / 2.0
    parts.add("bark", frustum((0.0, 0.0), 0.0, trunk + rz, tr, tr * 0.6, 10))
    parts.add("leaves", ellipsoid((0.0, 0.0, trunk + rz), (l / 2, w / 2, rz), 2))
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
    parts.add("metal", frustum((0.0, 0.0), 0.0, h - 0.06, l / 2 * 0.9, l / 2, 10))
    parts.add("paint_band", frustum((0.0, 0.0), h - 0.06, h, l / 2, l / 2 * 0.6, 10))
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
}
del math, np
