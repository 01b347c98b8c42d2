"""Car, van, truck and bus built from boxes, trapezoids and wheels.

Built in the object frame with the ground at z = 0 (fit_to_dims centres it afterwards): x from
-l/2 (rear) to +l/2 (front), y across. Every design reaches exactly +-l/2 (bumpers and lights),
+-w/2 (mirrors or the widest body) and 0..h (tyres to roof), so the fit is an identity up to
rounding and wheels stay round. What makes each one a car to a detector: wheels with rims, a
glass greenhouse with a sloped windshield, head- and taillights, bumpers, mirrors.
"""

from __future__ import annotations

from scenes.assets.parts import Parts, box, trapezoid_x, wheel

TYRE_WIDTH = 0.22


def _wheels(parts: Parts, xs, y_outer: float, radius: float, width: float = TYRE_WIDTH, twin: bool = False) -> None:
    for x in xs:
        for side in (-1.0, 1.0):
            y = side * (y_outer - width / 2.0)
            parts.add("tyre", wheel((x, y, radius), radius, width))
            parts.add("rim", wheel((x, y + side * 0.005, radius), 0.58 * radius, width))
            if twin:
                y2 = side * (y_outer - 1.5 * width - 0.02)
                parts.add("tyre", wheel((x, y2, radius), radius, width))


def _lights(parts: Parts, l: float, w: float, z: float, size_z: float, inset_y: float, depth: float = 0.04) -> None:
    """Headlights at the front face (x = l/2), taillights at the rear (x = -l/2)."""
    for side in (-1.0, 1.0):
        y0, y1 = sorted((side * (w / 2 - inset_y), side * (w / 2 - inset_y - 0.28)))
        parts.add("headlight", box((l / 2 - depth, y0, z), (l / 2, y1, z + size_z)))
        parts.add("taillight", box((-l / 2, y0, z), (-l / 2 + depth, y1, z + size_z)))


def car(dims, p: dict) -> Parts:
    l, w, h = dims
    style = p.get("style", "sedan")
    r = float(p.get("wheel_radius", 0.32))
    parts = Parts()
    bw = w - 0.12  # body width; the mirrors reach w
    clear = 0.2 if style == "suv" else 0.15
    belt = h * (0.60 if style == "suv" else 0.56)
    # Lower body with bumpers at both ends (the bumpers define +-l/2).
    parts.add("paint", trapezoid_x(-l / 2 + 0.04, l / 2 - 0.04, -l / 2 + 0.08, l / 2 - 0.12, bw, bw - 0.04, clear + 0.12, belt))
    parts.add("trim", box((-l / 2, -bw / 2 + 0.03, clear), (l / 2, bw / 2 - 0.03, clear + 0.22)))
    hood = {"sedan": 0.30, "hatchback": 0.28, "wagon": 0.28, "suv": 0.25}.get(style, 0.3) * l
    rear = {"sedan": 0.20, "hatchback": 0.05, "wagon": 0.05, "suv": 0.06}.get(style, 0.2) * l
    rake = {"sedan": 0.45, "hatchback": 0.30, "wagon": 0.12, "suv": 0.14}.get(style, 0.3)
    xf0, xr0 = l / 2 - hood, -l / 2 + rear
    xf1, xr1 = xf0 - 0.55 * (h - belt) / 0.6, xr0 + rake
    top = h - 0.05
    parts.add("glass", trapezoid_x(xr0, xf0, xr1, xf1, bw - 0.04, bw - 0.30, belt, top))
    parts.add("paint", trapezoid_x(xr1 + 0.02, xf1 - 0.02, xr1 + 0.05, xf1 - 0.05, bw - 0.30, bw - 0.34, top, h))
    mid = (xr1 + xf1) / 2.0
    for side in (-1.0, 1.0):  # B-pillars
        y0, y1 = sorted((side * (bw / 2 - 0.14), side * (bw / 2 - 0.02)))
        parts.add("paint", box((mid - 0.05, y0, belt), (mid + 0.05, y1, top)))
        ym0, ym1 = sorted((side * bw / 2, side * w / 2))  # mirrors
        parts.add("paint", box((xf0 - 0.22, ym0, belt + 0.02), (xf0 - 0.08, ym1, belt + 0.14)))
    wheelbase = min(0.60 * l, l - 2 * r - 0.9)
    _wheels(parts, (wheelbase / 2, -wheelbase / 2), bw / 2 + 0.005, r)
    _lights(parts, l, bw, belt - 0.16, 0.10, 0.08)
    return parts


def van(dims, p: dict) -> Parts:
    l, w, h = dims
    r = float(p.get("wheel_radius", 0.35))
    parts = Parts()
    bw = w - 0.14
    clear, belt = 0.2, 0.48 * h
    nose = 0.75  # short bonnet
    parts.add("paint", trapezoid_x(-l / 2 + 0.04, l / 2 - 0.04, -l / 2 + 0.04, l / 2 - 0.10, bw, bw, clear + 0.12, belt))
    parts.add("trim", box((-l / 2, -bw / 2 + 0.03, clear), (l / 2, bw / 2 - 0.03, clear + 0.22)))
    cab = 1.6  # windshield and front doors
    x_cab = l / 2 - nose - cab
    parts.add("paint", box((-l / 2 + 0.04, -bw / 2, belt), (x_cab, bw / 2, h)))  # load box
    parts.add("glass", trapezoid_x(x_cab, l / 2 - nose, x_cab, l / 2 - nose - 0.7, bw - 0.04, bw - 0.1, belt, h - 0.08))
    parts.add("paint", box((x_cab, -bw / 2 + 0.05, h - 0.08), (l / 2 - nose - 0.72, bw / 2 - 0.05, h)))
    if p.get("style") == "windowed":
        for side in (-1.0, 1.0):
            y0, y1 = sorted((side * bw / 2, side * (bw / 2 + 0.01)))
            parts.add("glass", box((-l / 2 + 0.5, y0, belt + 0.15), (x_cab - 0.15, y1, h - 0.3)))
    parts.add("glass", box((-l / 2 + 0.01, -bw / 2 + 0.2, belt + 0.2), (-l / 2 + 0.04, bw / 2 - 0.2, h - 0.3)))
    for side in (-1.0, 1.0):
        ym0, ym1 = sorted((side * bw / 2, side * w / 2))
        parts.add("trim", box((l / 2 - nose - 0.3, ym0, belt + 0.05), (l / 2 - nose - 0.12, ym1, belt + 0.3)))
    wheelbase = min(0.62 * l, l - 2 * r - 1.0)
    _wheels(parts, (l / 2 - nose - 0.25 - r * 0.2, l / 2 - nose - 0.25 - r * 0.2 - wheelbase), bw / 2 + 0.005, r)
    _lights(parts, l, bw, belt - 0.2, 0.14, 0.06)
    return parts


def truck(dims, p: dict) -> Parts:
    l, w, h = dims
    r = float(p.get("wheel_radius", 0.5))
    cab_len = float(p.get("cab_length", 2.1))
    parts = Parts()
    cab_w, cab_h = w - 0.18, min(h, 2.95)
    x_cab = l / 2 - cab_len
    # Cab: body, windshield on the upper front, roof; mirrors reach out to the cargo width.
    parts.add("cab", box((x_cab, -cab_w / 2, 0.45), (l / 2 - 0.03, cab_w / 2, cab_h)))
    parts.add("glass", box((l / 2 - 0.03, -cab_w / 2 + 0.1, 0.55 * cab_h + 0.4), (l / 2, cab_w / 2 - 0.1, cab_h - 0.15)))
    parts.add("trim", box((l / 2 - 0.12, -cab_w / 2, 0.35), (l / 2, cab_w / 2, 0.75)))
    for side in (-1.0, 1.0):
        y0, y1 = sorted((side * (cab_w / 2 - 0.4), side * (cab_w / 2 + 0.001)))
        parts.add("glass", box((l / 2 - 1.0, y0, 0.55 * cab_h + 0.4), (l / 2 - 0.15, y1, cab_h - 0.2)))
    # Chassis and cargo.
    parts.add("trim", box((-l / 2 + 0.3, -0.5, 0.55), (x_cab, 0.5, 1.0)))
    x0, x1 = -l / 2, x_cab - 0.15
    if p.get("style") == "flatbed":
        parts.add("cargo", box((x0, -w / 2, 1.0), (x1, w / 2, 1.25)))
        # A load of stacked crates that reaches the drawn height.
        n = max(1, int((x1 - x0) // 2.2))
        step = (x1 - x0 - 0.3) / n
        for i in range(n):
            top = h if i % 2 == 0 else 1.25 + 0.7 * (h - 1.25)
            parts.add("crate", box((x0 + 0.15 + i * step + 0.05, -w / 2 + 0.1, 1.25), (x0 + 0.15 + (i + 1) * step - 0.05, w / 2 - 0.1, top)))
    else:
        parts.add("cargo", box((x0, -w / 2, 1.0), (x1, w / 2, h)))
    axles = int(p.get("axles", 2))
    rear = [-l / 2 + 1.3 + r] + ([-l / 2 + 1.3 + 3.2 * r] if axles >= 3 else [])
    _wheels(parts, [l / 2 - cab_len / 2 - 0.1], cab_w / 2 + 0.005, r, 0.3)
    _wheels(parts, rear, w / 2 - 0.05, r, 0.3, twin=True)
    _lights(parts, l, cab_w, 0.8, 0.16, 0.1)
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
    # Doors on the kerb (right, -y) side.
    doors = int(p.get("doors", 2))
    for i in range(doors):
        x = l / 2 - 1.0 - i * (l - 2.2) / max(doors - 1, 1)
        parts.add("glass", box((x - 0.6, -w / 2 - 0.001, 0.35), (x + 0.6, -bw / 2 + 0.05, 2.4)))
    parts.add("glass", box((l / 2 - 0.02, -bw / 2 + 0.1, 1.0), (l / 2, bw / 2 - 0.1, roof - 0.35)))
    parts.add("glass", box((-l / 2, -bw / 2 + 0.2, 1.5), (-l / 2 + 0.02, bw / 2 - 0.2, roof - 0.35)))
    parts.add("sign", box((l / 2 - 0.02, -bw / 2 + 0.3, roof - 0.3), (l / 2, bw / 2 - 0.3, roof - 0.05)))
    parts.add("trim", box((l / 2 - 0.1, -bw / 2, 0.32), (l / 2, bw / 2, 0.6)))
    parts.add("trim", box((-l / 2, -bw / 2, 0.32), (-l / 2 + 0.1, bw / 2, 0.6)))
    _wheels(parts, (l / 2 - 2.5, -l / 2 + 3.2), bw / 2 - 0.02, r, 0.3)
    _lights(parts, l, bw, 0.65, 0.2, 0.15)
    return parts
