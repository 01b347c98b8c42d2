"""Car (sedan, hatchback, wagon, SUV, pickup), van, box truck, bus and tram.

Built in the object frame with the ground at z = 0 (fit_to_dims centres it afterwards): x from
-l/2 (rear) to +l/2 (front), y across. Every design reaches exactly +-l/2 (bumpers, plates,
lights), +-w/2 (mirrors or the widest body) and 0..h (tyres to roof), so the fit is an identity
up to rounding and wheels stay round.

Why the ends differ so much: a monocular detector has to tell a vehicle's front from its back
(its heading), and today's boxy bodies gave it little to go on. So each design carries the cues
people use: at the FRONT a bonnet that slopes down to a low nose, a raked windscreen, white
headlights at the nose's top corners, a dark grille and intake between them, a plate low on
the bumper and mirrors by the windscreen base; at the BACK an upright or short tail, red
taillights wrapping the rear corners, a plate higher up, a dark diffuser or under-run bar.
Wheel arches and sills frame the wheels from the side. The body is a side profile extruded
across (`prism_y`), so the silhouette itself (low nose, high tail) is asymmetric too.

Triangle budget: a car is a few hundred triangles (wheels are 12-gons); the raster preview
builds every agent in view every frame.
"""

from __future__ import annotations

import math

import numpy as np

from omnigen.scenes.assets.parts import Parts, Piece, box, cylinder_between, hexahedron, prism_y, trapezoid_x, wheel

TYRE_WIDTH = 0.22
WHEEL_SECTIONS = 12
PLATE_W, PLATE_H = 0.52, 0.11  # EU plate 520 x 110 mm


def _wheels(parts: Parts, xs, y_outer: float, radius: float, width: float = TYRE_WIDTH, twin: bool = False,
            sections: int = WHEEL_SECTIONS) -> None:
    for x in xs:
        for side in (-1.0, 1.0):
            y = side * (y_outer - width / 2.0)
            parts.add("tyre", wheel((x, y, radius), radius, width, sections))
            parts.add("rim", wheel((x, y + side * 0.006, radius), 0.6 * radius, width, sections))
            if twin:
                y2 = side * (y_outer - 1.5 * width - 0.02)
                parts.add("tyre", wheel((x, y2, radius), radius, width, sections))


_ARCH = np.radians([15.0, 65.0, 115.0, 165.0])


def _arches(parts: Parts, role: str, xs, radius: float, y_in: float, y_out: float) -> None:
    """A lip over each wheel on both sides: three segments of a band around the upper half.

    Each segment is a quad profile extruded across (prism_y's solid), built for all segments at
    once: a car has 24 of them and this runs for every car in view every frame.
    """
    ri, ro = radius + 0.03, radius + 0.09
    c, s = np.cos(_ARCH), np.sin(_ARCH)
    # (3, 4, 2) profiles, counter-clockwise in (x, z): inner a0, outer a0, outer a1, inner a1.
    prof = np.stack([np.stack([ri * c[:-1], ri * s[:-1]], -1), np.stack([ro * c[:-1], ro * s[:-1]], -1),
                     np.stack([ro * c[1:], ro * s[1:]], -1), np.stack([ri * c[1:], ri * s[1:]], -1)], axis=1)
    prof[..., 1] += radius
    faces = prism_y(prof[0], 0.0, 1.0).faces
    verts = []
    for x in xs:
        for ya, yb in ((-y_out, -y_in), (y_in, y_out)):
            v = np.empty((3, 8, 3))
            v[:, :4, 0], v[:, 4:, 0] = prof[..., 0] + x, prof[..., 0] + x
            v[:, :4, 2], v[:, 4:, 2] = prof[..., 1], prof[..., 1]
            v[:, :4, 1], v[:, 4:, 1] = ya, yb
            verts.append(v.reshape(-1, 3))
    v = np.concatenate(verts)
    k = len(v) // 8
    parts.add(role, Piece(v, (faces[None, :, :] + 8 * np.arange(k)[:, None, None]).reshape(-1, 3)))


def _pair(parts: Parts, role: str, x0: float, x1: float, y_out: float, width: float, z0: float, z1: float) -> None:
    """Two boxes mirrored about y = 0, each from |y| = y_out inwards by `width`."""
    for side in (-1.0, 1.0):
        parts.add(role, box((x0, side * y_out, z0), (x1, side * (y_out - width), z1)))


def _plate(parts: Parts, p: dict, x0: float, x1: float, z0: float, rear: bool) -> None:
    """A licence plate; rear plates are yellow where p['plate'] says so (UK, NL style)."""
    role = "plate_yellow" if rear and p.get("plate") == "yellow" else "plate"
    parts.add(role, box((x0, -PLATE_W / 2, z0), (x1, PLATE_W / 2, z0 + PLATE_H)))


def _greenhouse_strip(parts: Parts, role: str, x0: float, x1: float, yb: float, yt: float, z0: float, z1: float,
                      thick: float = 0.05) -> None:
    """A pillar on both sides following a greenhouse side that runs from |y| = yb at z0 to yt at z1."""
    for side in (-1.0, 1.0):
        b0, b1 = sorted((side * (yb + 0.012), side * (yb - thick)))
        t0, t1 = sorted((side * (yt + 0.012), side * (yt - thick)))
        parts.add(role, hexahedron([(x0, b0), (x1, b0), (x1, b1), (x0, b1)], z0, [(x0, t0), (x1, t0), (x1, t1), (x0, t1)], z1))


# ---------------------------------------------------------------------------------------------
# Cars
# ---------------------------------------------------------------------------------------------

HOOD = {"sedan": 0.27, "hatchback": 0.25, "wagon": 0.26, "suv": 0.24, "pickup": 0.25}  # of l
RAKE_FRONT = {"sedan": 1.25, "hatchback": 1.15, "wagon": 1.2, "suv": 0.9, "pickup": 0.75}  # run / rise
RAKE_REAR = {"sedan": 0.95, "hatchback": 0.75, "wagon": 0.15, "suv": 0.2, "pickup": 0.1}
DECK = {"sedan": 0.17, "hatchback": 0.025, "wagon": 0.025, "suv": 0.03, "pickup": 0.0}  # boot, of l


def car(dims, p: dict) -> Parts:
    l, w, h = dims
    style = p.get("style", "sedan")
    if style not in HOOD:
        style = "sedan"
    r = float(p.get("wheel_radius", 0.32))
    parts = Parts()
    tall = style in ("suv", "pickup")
    bw = w - 0.14  # body width; the mirrors reach w
    clear = 0.18 if tall else 0.13
    belt = h * (0.6 if tall else 0.56)
    top = h - 0.035  # the roof slab sits on the greenhouse
    nose_z = belt - (0.09 if tall else 0.15)
    gh = top - belt
    xf0 = l / 2 - HOOD[style] * l
    xf1 = xf0 - RAKE_FRONT[style] * gh
    if style == "pickup":
        xr1 = xf1 - float(p.get("cab_roof", 1.25))
        xr0 = xr1 - RAKE_REAR[style] * gh
    else:
        xr0 = -l / 2 + max(DECK[style] * l, 0.08)
        xr1 = xr0 + RAKE_REAR[style] * gh
    if xf1 - xr1 < 0.8:  # a short car keeps a roof: pull the rear window back
        xr1 = max(xf1 - 0.8, -l / 2 + 0.2)
        xr0 = max(min(xr0, xr1 - 0.05), -l / 2 + 0.08)
    roof_role = "stripe" if p.get("two_tone") else "paint"
    # Lower body: a side profile, low raked nose, bonnet rising to the windscreen, upright tail.
    nose = [(l / 2 - 0.2, clear), (l / 2, clear + 0.22), (l / 2 - 0.07, nose_z), (xf0, belt)]
    if style == "pickup":
        x_cb = xr0 - 0.02  # cab back
        parts.add("paint", prism_y([(x_cb, clear)] + nose + [(x_cb, belt)], -bw / 2, bw / 2))
        bed_floor = belt - 0.42
        parts.add("paint", box((-l / 2 + 0.04, -bw / 2, clear), (x_cb, bw / 2, bed_floor)))
        parts.add("trim", box((-l / 2 + 0.08, -bw / 2 + 0.06, bed_floor), (x_cb - 0.06, bw / 2 - 0.06, bed_floor + 0.02)))
        for side in (-1.0, 1.0):  # bed walls
            parts.add("paint", box((-l / 2 + 0.04, side * bw / 2, bed_floor), (x_cb, side * (bw / 2 - 0.06), belt)))
        parts.add("paint", box((x_cb - 0.06, -bw / 2, bed_floor), (x_cb, bw / 2, belt)))  # bulkhead
        parts.add("paint", box((-l / 2 + 0.02, -bw / 2, clear + 0.2), (-l / 2 + 0.08, bw / 2, belt)))  # tailgate
        parts.add("trim", box((-l / 2, -bw / 2 + 0.05, clear + 0.02), (-l / 2 + 0.16, bw / 2 - 0.05, clear + 0.2)))  # step bumper
        _pair(parts, "taillight", -l / 2 + 0.006, -l / 2 + 0.1, bw / 2 + 0.004, 0.13, belt - 0.36, belt - 0.04)
        _plate(parts, p, -l / 2 + 0.006, -l / 2 + 0.03, clear + 0.3, rear=True)
    else:
        tail_top = belt - 0.01
        parts.add("paint", prism_y([(-l / 2 + 0.18, clear)] + nose + [(xr0, belt), (-l / 2 + 0.04, tail_top), (-l / 2, clear + 0.28)],
                                   -bw / 2, bw / 2))
        # Taillights wrap the rear corners; tall tails (hatchback, wagon, SUV) get vertical ones.
        tz0, tz1 = (belt - 0.2, belt + 0.1) if style != "sedan" else (belt - 0.17, belt - 0.05)
        _pair(parts, "taillight", -l / 2 + 0.012, -l / 2 + 0.2, bw / 2 + 0.004, 0.3 if style == "sedan" else 0.2, tz0, tz1)
        parts.add("trim", box((-l / 2 + 0.04, -bw / 2 + 0.25, clear + 0.02), (-l / 2 + 0.2, bw / 2 - 0.25, clear + 0.11)))  # diffuser
        _plate(parts, p, -l / 2 + 0.001, -l / 2 + 0.06, clear + 0.3, rear=True)
        if style in ("hatchback", "suv", "wagon"):  # roof spoiler over the tailgate
            parts.add(roof_role, trapezoid_x(xr1 - 0.02, xr1 + 0.3, xr1 + 0.01, xr1 + 0.3, bw - 0.4, bw - 0.42, top - 0.05, h))
    # Greenhouse: glass with a tumblehome, a roof slab, B-pillars (and C-pillars on long roofs).
    yb, yt = (bw - 0.08) / 2, (bw - 0.36) / 2
    parts.add("glass", trapezoid_x(xr0, xf0, xr1, xf1, 2 * yb, 2 * yt, belt, top))
    parts.add(roof_role, trapezoid_x(xr1 - 0.01, xf1 + 0.01, xr1 + 0.03, xf1 - 0.03, 2 * yt + 0.02, 2 * yt - 0.02, top, h))
    pillar = "trim" if p.get("black_pillars") else "paint"
    xm = xf1 - 0.45 * (xf1 - xr1) if style != "pickup" else xf1 - 0.55 * (xf1 - xr1)
    _greenhouse_strip(parts, pillar, xm - 0.05, xm + 0.05, yb, yt, belt, top)
    if style in ("wagon", "suv"):
        _greenhouse_strip(parts, pillar, xr1 + 0.25, xr1 + 0.4, yb, yt, belt, top)
    # The windscreen's dark cowl at its base (seen from the front and above), and the high-mounted
    # stop lamp at the rear window's top (seen from behind; red at night).
    parts.add("trim", box((xf0 - 0.1, -(yb - 0.12), belt - 0.01), (xf0 + 0.03, yb - 0.12, belt + 0.03)))
    parts.add("taillight", box((xr1 - 0.06, -0.2, top - 0.05), (xr1 + 0.02, 0.2, top - 0.01)))
    # Front: headlights at the nose's top corners, grille and intake, plate low on the bumper.
    lamp_h, lamp_w = {0: (0.07, 0.36), 1: (0.11, 0.3), 2: (0.14, 0.24)}[int(p.get("lamp_style", 1)) % 3]
    _pair(parts, "headlight", l / 2 - 0.26, l / 2 - 0.055, bw / 2 - 0.04, lamp_w, nose_z - lamp_h, nose_z + 0.015)
    gw = float(p.get("grille_width", 0.5)) * (bw - 2 * lamp_w - 0.1)
    parts.add("trim", box((l / 2 - 0.12, -gw / 2, clear + 0.24), (l / 2 - 0.015, gw / 2, nose_z - 0.025)))
    parts.add("trim", box((l / 2 - 0.2, -(bw / 2 - 0.35), clear + 0.03), (l / 2 - 0.05, bw / 2 - 0.35, clear + 0.12)))
    _plate(parts, p, l / 2 - 0.1, l / 2 - 0.004, clear + 0.1, rear=False)
    # Mirrors at the windscreen base reach the drawn width.
    mirror = "trim" if p.get("black_mirrors") else "paint"
    for side in (-1.0, 1.0):
        parts.add(mirror, box((xf0 - 0.24, side * (bw / 2 - 0.02), belt + 0.02), (xf0 - 0.08, side * w / 2, belt + 0.15)))
    wheelbase = min(0.6 * l, l - 2 * r - 0.9)
    xs = (wheelbase / 2 + (0.05 if style == "pickup" else 0.0), -wheelbase / 2)
    _wheels(parts, xs, bw / 2 + 0.01, r)
    _arches(parts, "trim" if tall or p.get("black_arches") else "paint", xs, r, bw / 2 - 0.04, bw / 2 + 0.012)
    sill0, sill1 = xs[1] + r + 0.12, xs[0] - r - 0.12
    if sill1 > sill0:
        _pair(parts, "trim", sill0, sill1, bw / 2 + 0.004, 0.06, clear, clear + 0.09)
    return parts


# ---------------------------------------------------------------------------------------------
# Van, truck, bus, tram
# ---------------------------------------------------------------------------------------------


def van(dims, p: dict) -> Parts:
    l, w, h = dims
    r = float(p.get("wheel_radius", 0.35))
    style = p.get("style", "panel")
    parts = Parts()
    bw = w - 0.14
    clear, belt = 0.2, 0.49 * h
    nose_z = belt - 0.12
    x_ws0 = l / 2 - 0.78  # windscreen base (short bonnet)
    x_ws1 = x_ws0 - 0.85 * (h - 0.06 - belt)  # windscreen top: raked
    back = -l / 2 + 0.02
    # Two convex profiles: the lower body with its short bonnet, the tall box behind the windscreen.
    parts.add("paint", prism_y([(back + 0.1, clear), (l / 2 - 0.22, clear), (l / 2 - 0.03, clear + 0.26), (l / 2 - 0.09, nose_z),
                                (x_ws0, belt), (back, belt), (back, clear + 0.3)], -bw / 2, bw / 2))
    parts.add("paint", prism_y([(back, belt), (x_ws0, belt), (x_ws1, h - 0.06), (x_ws1 - 0.15, h), (back + 0.04, h), (back, h - 0.08)],
                               -bw / 2, bw / 2))
    # Windscreen: a slab 1.5 cm proud of the raked edge.
    dx, dz = x_ws1 - x_ws0, h - 0.06 - belt
    n = math.hypot(dx, dz)
    ox, oz = dz / n * 0.015, -dx / n * 0.015  # outward (forward and up)
    a0, a1 = (x_ws0 + 0.04 * dx, belt + 0.04 * dz), (x_ws0 + 0.95 * dx, belt + 0.95 * dz)
    parts.add("glass", prism_y([a0, a1, (a1[0] + ox, a1[1] + oz), (a0[0] + ox, a0[1] + oz)], -(bw / 2 - 0.07), bw / 2 - 0.07))
    for side in (-1.0, 1.0):  # cab door windows
        parts.add("glass", box((x_ws1 - 0.85, side * (bw / 2 - 0.01), belt + 0.1), (x_ws1 + 0.1, side * (bw / 2 + 0.008), h - 0.25)))
        if style in ("windowed", "minibus"):
            z0 = belt + (0.05 if style == "minibus" else 0.15)
            parts.add("glass", box((back + 0.45, side * (bw / 2 - 0.01), z0), (x_ws1 - 1.0, side * (bw / 2 + 0.008), h - 0.25)))
        parts.add("trim", box((x_ws0 - 0.3, side * (bw / 2 - 0.02), belt + 0.05), (x_ws0 - 0.14, side * w / 2, belt + 0.38)))  # mirror
    # Rear: upright doors with a split, windows, vertical taillights at the corners, plate, bumper.
    parts.add("trim", box((back - 0.01, -0.012, clear + 0.35), (back + 0.02, 0.012, h - 0.12)))
    if style != "panel" or p.get("rear_windows", True):
        for side in (-1.0, 1.0):
            parts.add("glass", box((back - 0.012, side * 0.05, h - 0.75), (back + 0.02, side * (bw / 2 - 0.14), h - 0.25)))
    _pair(parts, "taillight", back - 0.015, back + 0.1, bw / 2 + 0.003, 0.1, clear + 0.35, clear + 0.9)
    parts.add("trim", box((-l / 2, -(bw / 2 - 0.02), clear + 0.04), (back + 0.22, bw / 2 - 0.02, clear + 0.3)))
    _plate(parts, p, back - 0.016, back + 0.02, clear + 0.4, rear=True)
    # Front: bumper, grille between the headlights, plate on the bumper.
    parts.add("trim", box((l / 2 - 0.25, -(bw / 2 - 0.02), clear), (l / 2 - 0.015, bw / 2 - 0.02, clear + 0.25)))
    _plate(parts, p, l / 2 - 0.03, l / 2, clear + 0.07, rear=False)
    parts.add("trim", box((l / 2 - 0.12, -(bw / 2 - 0.36), clear + 0.27), (l / 2 - 0.025, bw / 2 - 0.36, nose_z - 0.05)))
    _pair(parts, "headlight", l / 2 - 0.22, l / 2 - 0.045, bw / 2 - 0.03, 0.28, nose_z - 0.17, nose_z - 0.02)
    xs = (l / 2 - 0.85, back + 0.95)
    _wheels(parts, xs, bw / 2 + 0.01, r)
    _arches(parts, "trim", xs, r, bw / 2 - 0.04, bw / 2 + 0.012)
    return parts


def truck(dims, p: dict) -> Parts:
    l, w, h = dims
    r = float(p.get("wheel_radius", 0.5))
    cab_len = float(p.get("cab_length", 2.1))
    parts = Parts()
    cab_w, cab_h = w - 0.18, min(h, 2.95)
    x_cab = l / 2 - cab_len
    front = l / 2 - 0.03
    # Cab: a slightly raked upper front; windscreen, sun visor, grille, bumper with lights, plate.
    z_ws = 0.55 * cab_h + 0.35
    parts.add("cab", prism_y([(x_cab, 0.45), (front, 0.45), (front, z_ws), (front - 0.18, cab_h), (x_cab, cab_h)], -cab_w / 2, cab_w / 2))
    parts.add("glass", prism_y([(front - 0.02, z_ws + 0.05), (front - 0.15, cab_h - 0.2), (front - 0.13, cab_h - 0.19), (front + 0.0, z_ws + 0.06)],
                               -(cab_w / 2 - 0.1), cab_w / 2 - 0.1))
    parts.add("trim", box((front - 0.2, -cab_w / 2, cab_h - 0.16), (front - 0.02, cab_w / 2, cab_h - 0.08)))  # sun visor
    parts.add("trim", box((front - 0.02, -(cab_w / 2 - 0.45), 0.85), (front + 0.015, cab_w / 2 - 0.45, z_ws - 0.1)))  # grille
    parts.add("trim", box((l / 2 - 0.16, -cab_w / 2, 0.35), (l / 2 - 0.01, cab_w / 2, 0.75)))  # bumper
    _pair(parts, "headlight", l / 2 - 0.05, l / 2, cab_w / 2 - 0.06, 0.32, 0.52, 0.68)
    _plate(parts, p, l / 2 - 0.03, l / 2, 0.4, rear=False)
    if h - cab_h > 0.45 and p.get("style") != "flatbed":  # roof deflector up to the box
        parts.add("cab", trapezoid_x(x_cab + 0.1, front - 0.3, x_cab + 0.1, x_cab + 0.6, cab_w - 0.1, cab_w - 0.2, cab_h, min(h, cab_h + 0.9) - 0.02))
    for side in (-1.0, 1.0):
        y0, y1 = sorted((side * (cab_w / 2 - 0.4), side * (cab_w / 2 + 0.008)))
        parts.add("glass", box((l / 2 - 1.0, y0, z_ws), (l / 2 - 0.25, y1, cab_h - 0.2)))
        parts.add("trim", box((l / 2 - 0.4, side * cab_w / 2, 1.5), (l / 2 - 0.25, side * w / 2, 2.15)))  # mirror
    # Chassis and cargo.
    parts.add("trim", box((-l / 2 + 0.3, -0.5, 0.55), (x_cab, 0.5, 1.0)))
    x0, x1 = -l / 2 + 0.03, x_cab - 0.15
    if p.get("style") == "flatbed":
        parts.add("cargo", box((x0, -w / 2, 1.0), (x1, w / 2, 1.25)))
        n = max(1, int((x1 - x0) // 2.2))
        step = (x1 - x0 - 0.3) / n
        for i in range(n):
            top = h if i % 2 == 0 else 1.25 + 0.7 * (h - 1.25)
            parts.add("crate", box((x0 + 0.15 + i * step + 0.05, -w / 2 + 0.1, 1.25), (x0 + 0.15 + (i + 1) * step - 0.05, w / 2 - 0.1, top)))
    else:
        parts.add("cargo", box((x0, -w / 2, 1.0), (x1, w / 2, h)))
        parts.add("trim", box((x0 - 0.015, -0.01, 1.1), (x0 + 0.01, 0.01, h - 0.1)))  # rear door seam
        for side in (-1.0, 1.0):  # marker lights at the top rear corners
            parts.add("taillight", box((x0 - 0.015, side * (w / 2 - 0.05), h - 0.12), (x0 + 0.01, side * (w / 2 - 0.2), h - 0.05)))
    # Rear: a lamp panel with taillights and plate, the under-run bar below it.
    parts.add("trim", box((-l / 2 + 0.02, -(w / 2 - 0.1), 0.62), (-l / 2 + 0.3, w / 2 - 0.1, 1.0)))
    parts.add("trim", box((-l / 2, -(w / 2 - 0.12), 0.42), (-l / 2 + 0.12, w / 2 - 0.12, 0.56)))
    _pair(parts, "taillight", -l / 2 + 0.008, -l / 2 + 0.1, w / 2 - 0.12, 0.3, 0.7, 0.86)
    _plate(parts, p, -l / 2 + 0.008, -l / 2 + 0.04, 0.72, rear=True)
    axles = int(p.get("axles", 2))
    rear = [-l / 2 + 1.3 + r] + ([-l / 2 + 1.3 + 3.2 * r] if axles >= 3 else [])
    xf = l / 2 - cab_len / 2 - 0.1
    _wheels(parts, [xf], cab_w / 2 + 0.005, r, 0.3)
    _wheels(parts, rear, w / 2 - 0.05, r, 0.3, twin=True)
    g0, g1 = max(rear) + r + 0.25, xf - r - 0.25  # side guards between the axles
    if g1 - g0 > 0.5:
        _pair(parts, "trim", g0, g1, w / 2 - 0.06, 0.04, 0.45, 0.9)
    return parts


def bus(dims, p: dict) -> Parts:
    l, w, h = dims
    r = float(p.get("wheel_radius", 0.5))
    parts = Parts()
    bw = w - 0.02  # windows stand 1 cm proud on each side
    roof = h - 0.18
    parts.add("paint", box((-l / 2 + 0.02, -bw / 2, 0.32), (l / 2 - 0.02, bw / 2, roof)))
    parts.add("trim", box((-l / 2 + 3.0, -0.7, roof), (-l / 2 + 5.5, 0.7, h)))  # roof air conditioning
    parts.add("stripe", box((-l / 2 + 0.02, -bw / 2 - 0.002, 0.9), (l / 2 - 0.02, bw / 2 + 0.002, 1.05)))
    for side in (-1.0, 1.0):
        y0, y1 = sorted((side * bw / 2, side * w / 2))
        parts.add("glass", box((-l / 2 + 0.4, y0, 1.2), (l / 2 - 0.5, y1, roof - 0.25)))
        parts.add("trim", box((l / 2 - 0.3, side * (bw / 2 - 0.1), 1.9), (l / 2 - 0.15, side * w / 2, 2.35)))  # mirror
    # Doors on the kerb (right, -y) side.
    doors = int(p.get("doors", 2))
    for i in range(doors):
        x = l / 2 - 1.0 - i * (l - 2.2) / max(doors - 1, 1)
        parts.add("glass", box((x - 0.6, -w / 2 - 0.001, 0.35), (x + 0.6, -bw / 2 + 0.05, 2.4)))
    # Front: a tall windscreen down to 1 m, destination sign, low headlights, plate, bumper.
    parts.add("glass", box((l / 2 - 0.02, -bw / 2 + 0.1, 1.0), (l / 2, bw / 2 - 0.1, roof - 0.35)))
    parts.add("sign", box((l / 2 - 0.02, -bw / 2 + 0.3, roof - 0.3), (l / 2, bw / 2 - 0.3, roof - 0.05)))
    parts.add("trim", box((l / 2 - 0.1, -bw / 2, 0.32), (l / 2 - 0.01, bw / 2, 0.6)))
    _pair(parts, "headlight", l / 2 - 0.03, l / 2, bw / 2 - 0.12, 0.35, 0.65, 0.85)
    _plate(parts, p, l / 2 - 0.02, l / 2, 0.4, rear=False)
    # Rear: a small high window, the engine grille, vertical taillights, plate, bumper.
    parts.add("glass", box((-l / 2, -bw / 2 + 0.3, 1.7), (-l / 2 + 0.02, bw / 2 - 0.3, roof - 0.35)))
    parts.add("trim", box((-l / 2 + 0.005, -(bw / 2 - 0.35), 0.7), (-l / 2 + 0.03, bw / 2 - 0.35, 1.4)))
    parts.add("trim", box((-l / 2 + 0.01, -bw / 2, 0.32), (-l / 2 + 0.1, bw / 2, 0.6)))
    _pair(parts, "taillight", -l / 2, -l / 2 + 0.08, bw / 2 - 0.04, 0.16, 0.75, 1.6)
    _plate(parts, p, -l / 2 + 0.001, -l / 2 + 0.03, 0.42, rear=True)
    _wheels(parts, (l / 2 - 2.5, -l / 2 + 3.2), bw / 2 - 0.02, r, 0.3)
    return parts


def tram(dims, p: dict) -> Parts:
    """A low-floor articulated tram: 2-5 sections, bellows between them, a raked cab at each end.

    Trams are bidirectional; its heading (+x) is the end that shows the destination sign and the
    white headlights, the other end red taillights, as on a tram in service.
    """
    l, w, h = dims
    parts = Parts()
    n = int(p.get("sections", max(2, min(5, round(l / 9.0)))))
    roof = h - 0.45  # the folded pantograph stands above the roof
    floor, gap, rake = 0.3, 0.3, 0.5
    seg = (l - (n - 1) * gap) / n
    ws = w - 0.02  # body; the window band stands 1 cm proud
    parts.add("trim", box((-l / 2 + 0.3, -(ws / 2 - 0.05), 0.12), (l / 2 - 0.3, ws / 2 - 0.05, floor + 0.02)))  # skirts
    xm = 0.0
    for i in range(n):
        xa = -l / 2 + i * (seg + gap)
        xb = xa + seg
        if i == n // 2:
            xm = (xa + xb) / 2
        body_a, body_b = (xa + 1.2 if i == 0 else xa), (xb - 1.2 if i == n - 1 else xb)
        parts.add("paint", box((body_a, -ws / 2, floor), (body_b, ws / 2, roof)))
        for side in (-1.0, 1.0):
            parts.add("glass", box((xa + 0.35, side * (ws / 2 - 0.01), 1.05), (xb - 0.35, side * w / 2, roof - 0.35)))
            parts.add("stripe", box((xa + 0.05, side * (ws / 2 - 0.01), 0.7), (xb - 0.05, side * (ws / 2 + 0.004), 0.85)))
            xd = (xa + xb) / 2 + (0.25 * seg if i % 2 else -0.25 * seg) * (1 if side > 0 else -1)
            parts.add("glass", box((xd - 0.65, side * (ws / 2 - 0.01), floor + 0.05), (xd + 0.65, side * (ws / 2 + 0.006), 2.3)))
        if i < n - 1:
            parts.add("trim", box((xb - 0.05, -(ws / 2 - 0.15), floor + 0.1), (xb + gap + 0.05, ws / 2 - 0.15, roof - 0.1)))  # bellows
        if i != n // 2:
            parts.add("trim", box((xa + 1.2, -0.65, roof), (xb - 1.2, 0.65, roof + 0.3)))  # roof equipment
        bx = (xa + xb) / 2
        for ax in (bx - 0.9, bx + 0.9):  # one bogie per section, on standard gauge
            for side in (-1.0, 1.0):
                parts.add("tyre", wheel((ax, side * 0.72, 0.33), 0.33, 0.12, 8))
    # The two cab ends: raked hexahedra narrowing upward.
    for sgn in (1.0, -1.0):
        x_in, x_out = sgn * (l / 2 - 1.2), sgn * l / 2
        xt_out = sgn * (l / 2 - rake)
        lo_x, hi_x = sorted((x_in, x_out))
        tlo, thi = sorted((x_in, xt_out))
        parts.add("paint", hexahedron([(lo_x, -ws / 2), (hi_x, -ws / 2), (hi_x, ws / 2), (lo_x, ws / 2)], floor,
                                      [(tlo, -ws / 2 + 0.12), (thi, -ws / 2 + 0.12), (thi, ws / 2 - 0.12), (tlo, ws / 2 - 0.12)], roof))

        def face_x(z: float) -> float:
            return sgn * (l / 2 - rake * (z - floor) / (roof - floor))

        z0, z1 = 1.0, roof - 0.25
        q0, q1 = sorted((face_x(z0) - sgn * 0.05, face_x(z0) + sgn * 0.012))
        t0, t1 = sorted((face_x(z1) - sgn * 0.05, face_x(z1) + sgn * 0.012))
        yw0, yw1 = ws / 2 - 0.2, ws / 2 - 0.25
        parts.add("glass", hexahedron([(q0, -yw0), (q1, -yw0), (q1, yw0), (q0, yw0)], z0, [(t0, -yw1), (t1, -yw1), (t1, yw1), (t0, yw1)], z1))
        la, lb = sorted((face_x(0.62) - sgn * 0.06, sgn * l / 2))
        _pair(parts, "headlight" if sgn > 0 else "taillight", la, lb, ws / 2 - 0.2, 0.3, 0.48, 0.62)
        if sgn > 0:
            s0, s1 = sorted((face_x(roof - 0.05) - 0.06, face_x(roof - 0.28) + 0.012))
            parts.add("sign", box((s0, -(ws / 2 - 0.5), roof - 0.28), (s1, ws / 2 - 0.5, roof - 0.05)))
    # Pantograph (folded) on the middle section, reaching h.
    parts.add("metal", box((xm - 0.6, -0.5, roof), (xm + 0.6, 0.5, roof + 0.12)))
    for side in (-1.0, 1.0):
        parts.add("metal", cylinder_between((xm - 0.5, side * 0.3, roof + 0.12), (xm + 0.4, side * 0.1, h - 0.12), 0.03, 6))
    parts.add("metal", cylinder_between((xm + 0.4, 0.0, h - 0.12), (xm - 0.3, 0.0, h - 0.06), 0.03, 6))
    parts.add("metal", box((xm - 0.45, -0.8, h - 0.06), (xm - 0.15, 0.8, h)))
    return parts
