"""Pedestrian, cyclist (rider and bicycle as one object) and motorcyclist.

Body proportions are fractions of stature S from Drillis and Contini's segment table (shoulder
0.818 S, hip 0.530 S, knee 0.285 S, ankle 0.039 S, upper arm 0.186 S, forearm plus hand
0.254 S, foot length 0.152 S). The pose follows from the drawn cuboid, not the other way round:
a pedestrian's stride angle is solved from the drawn length l, the arms' abduction from the
drawn width w, and a rider's lean from the drawn height h, so the assembled design already fills
its box and fit_to_dims only corrects a few percent (the knees of a walker, a crouch limit).
"""

from __future__ import annotations

import math

import numpy as np

from omnigen.scenes.assets.parts import Parts, box, cylinder_between, ellipsoid, ring_y, trapezoid_x, wheel


def _head(parts: Parts, top: np.ndarray, s: float, p: dict, helmet: bool = False) -> None:
    """Head (and hair or helmet) whose highest point is `top`."""
    c = top - [0.0, 0.0, 0.07 * s]
    parts.add("skin", ellipsoid(c, (0.058 * s, 0.048 * s, 0.062 * s)))
    if helmet:
        parts.add("helmet", ellipsoid(c + [-0.004 * s, 0, 0.022 * s], (0.066 * s, 0.056 * s, 0.048 * s)))
        return
    parts.add("hair", ellipsoid(c + [-0.008 * s, 0, 0.03 * s], (0.06 * s, 0.05 * s, 0.04 * s)))
    if p.get("hair_long"):
        parts.add("hair", ellipsoid(c + [-0.035 * s, 0, -0.045 * s], (0.03 * s, 0.045 * s, 0.07 * s)))


def _limb(parts: Parts, role: str, a, b, radius: float) -> None:
    parts.add(role, cylinder_between(a, b, radius, 8))


def _knee(hip: np.ndarray, foot: np.ndarray, thigh: float, shank: float) -> np.ndarray:
    """Two-link inverse kinematics in the x-z plane, knee bending forward (+x) and up."""
    d_vec = foot - hip
    d = float(np.linalg.norm(d_vec))
    if d >= thigh + shank - 1e-6:
        return hip + d_vec * thigh / (thigh + shank)
    u = d_vec / d
    cos_g = (thigh**2 + d**2 - shank**2) / (2 * thigh * d)
    g = math.acos(max(-1.0, min(1.0, cos_g)))
    n = np.array([-u[2], 0.0, u[0]])  # u turned by 90 degrees in the x-z plane
    if n[0] < 0:
        n = -n
    return hip + thigh * (math.cos(g) * u + math.sin(g) * n)


def _stride_angle(span: float, leg_len: float, foot_len: float, max_deg: float) -> float:
    """Angle of each leg from the vertical so that the feet span `span`: 2 L sin(theta) + foot
    length = span, within 0 and max_deg."""
    return math.asin(float(np.clip((span - foot_len) / (2 * leg_len), 0.0, math.sin(math.radians(max_deg)))))


def _standing_leg(parts: Parts, s: float, hip: np.ndarray, knee: np.ndarray, ankle: np.ndarray) -> None:
    """Thigh, shank and a shoe flat on the ground under the ankle, toes forward (+x)."""
    _limb(parts, "bottom", hip, knee, 0.036 * s)
    _limb(parts, "bottom", knee, ankle, 0.028 * s)
    parts.add("shoes", box((ankle[0] - 0.04 * s, ankle[1] - 0.03 * s, 0.0), (ankle[0] + 0.112 * s, ankle[1] + 0.03 * s, ankle[2] + 0.02 * s)))


def pedestrian(dims, p: dict) -> Parts:
    l, w, h = dims
    s = h  # stature
    parts = Parts()
    r_arm, leg_len = 0.022 * s, 0.491 * s  # hip joint to ankle
    ankle_z, foot_len = 0.039 * s, 0.152 * s
    theta = _stride_angle(l, leg_len, foot_len, 28)  # the feet span the drawn length
    hip_z = ankle_z + leg_len * math.cos(theta)
    lead = 1.0 if float(p.get("phase", 0.5)) >= 0 else -1.0  # which leg is forward
    hip_half = 0.055 * s
    for side in (-1.0, 1.0):
        sgn = lead * side  # left leg (side +1) forward when lead = +1
        hip = np.array([0.0, side * hip_half, hip_z])
        # The foot is centred under the hip (ankle 0.036 S behind the foot's middle).
        ankle = np.array([sgn * leg_len * math.sin(theta) - 0.036 * s, side * hip_half, ankle_z])
        _standing_leg(parts, s, hip, hip + (ankle - hip) * (0.245 / 0.491), ankle)
    # Torso from the hips to the shoulders; the upper body keeps its length above the hips.
    shoulder_z = hip_z + 0.288 * s
    b = min(0.20 * s, w - 2 * r_arm - 0.06)  # shoulder joint distance, within the drawn width
    depth = 0.12 * s
    parts.add("bottom", trapezoid_x(-depth / 2, depth / 2, -depth / 2, depth / 2, 0.17 * s, 0.17 * s, hip_z - 0.04 * s, hip_z + 0.06 * s))
    parts.add("top", trapezoid_x(-depth / 2, depth / 2, -depth / 2 - 0.005 * s, depth / 2 + 0.005 * s, 0.165 * s, b + 0.03 * s, hip_z + 0.06 * s, shoulder_z + 0.02 * s))
    neck_top = shoulder_z + 0.06 * s
    _limb(parts, "skin", (0, 0, shoulder_z), (0.005 * s, 0, neck_top), 0.03 * s)
    _head(parts, np.array([0.01 * s, 0.0, hip_z + 0.47 * s]), s, p)
    # Arms: abducted to reach the drawn width, swinging against the legs.
    reach = 0.372 * s  # shoulder joint to the middle of the hand
    alpha = math.asin(float(np.clip((w / 2 - b / 2 - 0.016 * s) / reach, 0.0, 0.45)))
    phi = 0.8 * theta
    for side in (-1.0, 1.0):
        sgn = -lead * side
        sh = np.array([0.0, side * b / 2, shoulder_z])
        direction = np.array([sgn * math.sin(phi) * math.cos(alpha), side * math.sin(alpha), -math.cos(phi) * math.cos(alpha)])
        elbow = sh + direction * 0.186 * s
        hand = sh + direction * (0.186 + 0.146) * s
        _limb(parts, "top", sh, elbow, r_arm * 1.15)
        _limb(parts, "skin", elbow, hand, r_arm)
        parts.add("skin", ellipsoid(hand + direction * 0.04 * s, (0.03 * s, 0.016 * s, 0.05 * s)))
    if p.get("bag") and l / 2 >= depth / 2 + 0.1 * s:
        parts.add("bag", box((-depth / 2 - 0.09 * s, -0.09 * s, hip_z + 0.1 * s), (-depth / 2, 0.09 * s, shoulder_z - 0.03 * s)))
    return parts


def _rider(parts: Parts, s: float, hip: np.ndarray, shoulder: np.ndarray, bar: np.ndarray, grip_y: float, feet: list,
           p: dict, helmet: bool) -> None:
    """A rider seated at `hip`, hands on the handlebar `bar` at -grip_y and +grip_y, feet on `feet`
    (one per side, -y then +y)."""
    grips = [bar + [0, -grip_y, 0], bar + [0, grip_y, 0]]
    for side, foot in zip((-1.0, 1.0), feet):
        hj = hip + [0.0, side * 0.085 * s, 0.0]
        knee = _knee(hj, np.asarray(foot, dtype=np.float64), 0.245 * s, 0.25 * s)
        _limb(parts, "bottom", hj, knee, 0.036 * s)
        _limb(parts, "bottom", knee, foot, 0.028 * s)
        parts.add("shoes", box((foot[0] - 0.04 * s, foot[1] - 0.03 * s, foot[2] - 0.03 * s), (foot[0] + 0.1 * s, foot[1] + 0.03 * s, foot[2] + 0.02 * s)))
    up = shoulder - hip
    parts.add("bottom", ellipsoid(hip + [0, 0, 0.02 * s], (0.08 * s, 0.1 * s, 0.06 * s)))
    _limb(parts, "top", hip + 0.05 * up, shoulder, 0.085 * s)
    grip_span = abs(float(grips[1][1] - grips[0][1]))
    b = min(0.19 * s, grip_span - 0.04)
    for side, grip in zip((-1.0, 1.0), grips):
        sh = shoulder + [0.0, side * b / 2, 0.0]
        grip = np.asarray(grip, dtype=np.float64)
        elbow = (sh + grip) / 2 + [0.0, side * 0.005 * s, -0.04 * s]
        _limb(parts, "top", sh, elbow, 0.026 * s)
        _limb(parts, "skin", elbow, grip, 0.022 * s)
    u = up / np.linalg.norm(up)
    neck = shoulder + u * 0.05 * s
    _limb(parts, "skin", shoulder, neck, 0.03 * s)
    _head(parts, neck + [0.03 * s, 0, 0.14 * s], s, p, helmet)
    if p.get("bag"):  # a backpack on the rider's back, behind the torso's middle
        back = np.array([-u[2], 0.0, u[0]])
        parts.add("bag", ellipsoid(hip + 0.55 * up + back * 0.13 * s, (0.06 * s, 0.1 * s, 0.12 * s)))


def _pedals(parts: Parts, bb: np.ndarray, crank: float, arm: float) -> list[np.ndarray]:
    """Crank arms of length `arm` about the bottom bracket `bb` at angle `crank` (the -y one half a
    turn round) with their pedals; returns where the rider's feet rest, -y then +y."""
    feet = []
    for side, phase in ((-1.0, crank + math.pi), (1.0, crank)):
        pedal = bb + [arm * math.cos(phase), side * 0.12, arm * math.sin(phase)]
        _limb(parts, "trim", bb + [0, side * 0.06, 0], pedal, 0.012)
        feet.append(pedal + [0.0, 0.0, 0.03])
    return feet


def _leaning_shoulder(hip: np.ndarray, h: float, s: float, max_lean: float, min_lean: float = 0.0) -> np.ndarray:
    """The shoulder of a rider seated at `hip` whose torso leans forward by b so that the head top
    lands at h: hip + (torso + neck) cos(b) + head (0.14 s) = h, b kept within min_lean and
    max_lean degrees."""
    torso = 0.29 * s
    cos_b = float(np.clip((h - hip[2] - 0.14 * s) / (torso + 0.05 * s), math.cos(math.radians(max_lean)),
                          math.cos(math.radians(min_lean))))
    beta = math.acos(cos_b)
    return hip + torso * np.array([math.sin(beta), 0.0, cos_b])


def cyclist(dims, p: dict) -> Parts:
    l, w, h = dims
    parts = Parts()
    r = 0.34  # 700C / 28" wheel with tyre
    xr, xf = -l / 2 + r, l / 2 - r
    for x in (xr, xf):
        parts.add("tyre", ring_y((x, 0.0, r), r - 0.035, r, 0.035))
        parts.add("rim", ring_y((x, 0.0, r), r - 0.06, r - 0.035, 0.025))
        parts.add("rim", wheel((x, 0.0, r), 0.03, 0.1, 8))
    s = 1.02 * h
    bb = np.array([xr + 0.43 * (xf - xr) / 1.07, 0.0, 0.28])
    seat = np.array([bb[0] - 0.17, 0.0, 0.565 * s])
    head_top = np.array([xf - 0.27, 0.0, seat[2] - 0.05])
    head_bot = np.array([xf - 0.22, 0.0, seat[2] - 0.25])
    rear_hub, front_hub = np.array([xr, 0.0, r]), np.array([xf, 0.0, r])
    for a, b in ((rear_hub, bb), (bb, seat), (seat - [0, 0, 0.06], head_top), (bb, head_bot), (head_bot, head_top), (rear_hub, seat - [0, 0, 0.08])):
        _limb(parts, "frame", a, b, 0.018)
    for side in (-1.0, 1.0):
        _limb(parts, "frame", head_bot + [0, 0, 0.0], front_hub + [0, side * 0.05, 0.0], 0.013)
    parts.add("seat", box(seat + [-0.12, -0.07, 0.0], seat + [0.12, 0.07, 0.06]))
    bar = np.array([head_top[0] - 0.06, 0.0, head_top[2] + 0.12])
    _limb(parts, "frame", head_top, bar, 0.015)
    _limb(parts, "trim", bar - [0, w / 2, 0], bar + [0, w / 2, 0], 0.016)
    feet = _pedals(parts, bb, float(p.get("crank", 0.0)), 0.17)
    hip = seat + [0.0, 0.0, 0.09]
    shoulder = _leaning_shoulder(hip, h, s, 60)
    _rider(parts, s, hip, shoulder, bar, w / 2 - 0.06, feet, p, bool(p.get("helmet", False)))
    return parts


def motorcyclist(dims, p: dict) -> Parts:
    l, w, h = dims
    parts = Parts()
    r = 0.31
    xr, xf = -l / 2 + r, l / 2 - r
    for x in (xr, xf):
        parts.add("tyre", wheel((x, 0.0, r), r, 0.13, 18))
        parts.add("rim", wheel((x, 0.0, r), 0.6 * r, 0.14, 14))
    span = xf - xr
    parts.add("engine", box((xr + 0.35 * span, -0.2, 0.22), (xr + 0.72 * span, 0.2, 0.6)))
    parts.add("body", trapezoid_x(xr + 0.55 * span, xf - 0.22, xr + 0.58 * span, xf - 0.3, 0.34, 0.26, 0.6, 0.88))  # tank
    parts.add("seat", box((xr + 0.12 * span, -0.16, 0.7), (xr + 0.58 * span, 0.16, 0.82)))
    parts.add("body", trapezoid_x(xr - 0.15, xr + 0.35 * span, xr - 0.05, xr + 0.2 * span, 0.22, 0.18, 0.62, 0.76))  # tail
    head = np.array([xf - 0.22, 0.0, 0.95])
    for side in (-1.0, 1.0):
        _limb(parts, "trim", head + [0, side * 0.09, 0], (xf, side * 0.09, r), 0.025)
    parts.add("body", trapezoid_x(xf - 0.42, xf - 0.12, xf - 0.4, xf - 0.22, 0.36, 0.3, 0.72, 1.08))  # fairing
    parts.add("headlight", box((xf - 0.14, -0.08, 0.82), (xf - 0.1, 0.08, 0.92)))
    parts.add("taillight", box((xr - 0.16, -0.06, 0.68), (xr - 0.13, 0.06, 0.74)))
    parts.add("trim", cylinder_between((xr + 0.55 * span, -0.22, 0.35), (xr - 0.05, -0.22, 0.45), 0.05))  # exhaust
    bar = head + [-0.12, 0.0, 0.1]
    half = 0.85 * w / 2
    _limb(parts, "trim", bar - [0, half, 0], bar + [0, half, 0], 0.014)
    for side in (-1.0, 1.0):  # mirrors on stalks reach the drawn width
        stalk = bar + [0.0, side * (half - 0.04), 0.0]
        tip = bar + [0.02, side * (w / 2 - 0.06), 0.18]
        _limb(parts, "trim", stalk, tip, 0.01)
        y0, y1 = sorted((side * (w / 2 - 0.12), side * w / 2))
        parts.add("trim", box((tip[0] - 0.02, y0, tip[2] - 0.04), (tip[0] + 0.02, y1, tip[2] + 0.04)))
    s = 1.75 * (h / 1.55)
    hip = np.array([xr + 0.42 * span, 0.0, 0.9])
    shoulder = _leaning_shoulder(hip, h, s, 65, 8)
    feet = [np.array([hip[0] + 0.12, side * 0.22, 0.38]) for side in (-1.0, 1.0)]
    _rider(parts, s, hip, shoulder, bar, half - 0.05, feet, p, helmet=True)
    if p.get("top_box"):  # a luggage box over the tail
        parts.add("trim", box((xr - 0.12, -0.17, 0.78), (xr + 0.25, 0.17, 1.1)))
    return parts


def _wheel_pair(parts: Parts, x: float, y: float, z_hub: float, r: float, width: float) -> None:
    """A small wheel: tyre and rim discs (12-gons), axle along y."""
    parts.add("tyre", wheel((x, y, z_hub), r, width, 12))
    parts.add("rim", wheel((x, y, z_hub), 0.55 * r, width + 0.01, 12))


def tricyclist(dims, p: dict) -> Parts:
    """A rider on a three-wheeled cargo tricycle (box over the rear axle) or a cycle rickshaw.

    The front is a bicycle's (one steered wheel, handlebar, the rider pedalling); behind the
    rider, across the whole drawn width, the cargo box or the passenger bench under its hood.
    """
    l, w, h = dims
    parts = Parts()
    style = p.get("style", "cargo")
    r = 0.3
    box_len = float(np.clip(0.42 * l, 0.7, 1.3))
    x_box = -l / 2 + box_len  # front of the cargo box or bench
    x_ra = -l / 2 + box_len / 2
    for side in (-1.0, 1.0):
        _wheel_pair(parts, x_ra, side * (w / 2 - 0.1), r, r, 0.07)
    parts.add("frame", box((x_ra - 0.03, -(w / 2 - 0.1), r - 0.03), (x_ra + 0.03, w / 2 - 0.1, r + 0.03)))  # rear axle
    if style == "rickshaw":
        parts.add("cargo", box((-l / 2 + 0.1, -w / 2, 0.55), (x_box - 0.05, w / 2, 0.68)))  # seat
        parts.add("cargo", box((-l / 2 + 0.05, -w / 2, 0.68), (-l / 2 + 0.15, w / 2, 1.1)))  # backrest
        parts.add("cargo", trapezoid_x(-l / 2, -l / 2 + 0.5 * box_len, -l / 2 + 0.05, -l / 2 + 0.35 * box_len, w, w - 0.1, 1.1, h - 0.12))  # hood
        for side in (-1.0, 1.0):
            parts.add("frame", box((-l / 2 + 0.1, side * (w / 2 - 0.02), 0.3), (x_box - 0.1, side * (w / 2 - 0.05), 0.55)))
    else:
        parts.add("cargo", box((-l / 2, -w / 2, 0.5), (x_box, w / 2, 0.95)))
        if p.get("load"):
            parts.add("crate", box((-l / 2 + 0.1, -w / 2 + 0.1, 0.95), (x_box - 0.15, 0.05, 1.25)))
    parts.add("taillight", box((-l / 2 - 0.0, -0.08, 0.62), (-l / 2 + 0.02, 0.08, 0.68)) if style == "cargo" else
              box((-l / 2 + 0.0, -0.06, 0.45), (-l / 2 + 0.06, 0.06, 0.5)))
    xf = l / 2 - r
    _wheel_pair(parts, xf, 0.0, r, r, 0.06)
    s = (h - 0.09) / 0.95  # stature: an upright rider's head then lands near h
    seat = np.array([x_box + 0.25, 0.0, 0.5 * s])
    bb = np.array([seat[0] + 0.2, 0.0, 0.3])
    head_top = np.array([xf - 0.22, 0.0, seat[2] + 0.05])
    head_bot = np.array([xf - 0.17, 0.0, seat[2] - 0.2])
    front_hub = np.array([xf, 0.0, r])
    for a, b in ((np.array([x_box, 0.0, 0.5]), bb), (np.array([x_box, 0.0, 0.7]), seat - [0, 0, 0.05]), (bb, seat),
                 (bb, head_bot), (seat - [0, 0, 0.05], head_top), (head_bot, head_top)):
        _limb(parts, "frame", a, b, 0.022)
    for side in (-1.0, 1.0):
        _limb(parts, "frame", head_bot, front_hub + [0, side * 0.05, 0.0], 0.015)
    parts.add("seat", box(seat + [-0.12, -0.08, 0.0], seat + [0.12, 0.08, 0.07]))
    bar = np.array([head_top[0] - 0.05, 0.0, head_top[2] + 0.15])
    half = min(0.3, w / 2 - 0.05)
    _limb(parts, "frame", head_top, bar, 0.016)
    _limb(parts, "trim", bar - [0, half, 0], bar + [0, half, 0], 0.017)
    parts.add("headlight", box((xf - 0.12, -0.05, head_top[2] - 0.1), (xf - 0.06, 0.05, head_top[2] - 0.02)))
    feet = _pedals(parts, bb, float(p.get("crank", 0.0)), 0.16)
    hip = seat + [0.0, 0.0, 0.09]
    shoulder = _leaning_shoulder(hip, h, s, 60)
    _rider(parts, s, hip, shoulder, bar, half - 0.05, feet, {**p, "bag": False}, bool(p.get("helmet", False)))
    return parts


def barrow(dims, p: dict) -> Parts:
    """A walker pushing a wheelbarrow or a two-wheeled hand cart ahead of them (+x).

    The walker fills the rear ~0.6 m of the cuboid (legs in stride), hands on the handles at hip
    height; the barrow runs from the hands to the front, its wheel (or the cart's front) at +l/2.
    """
    l, w, h = dims
    parts = Parts()
    s = h
    x_w = -l / 2 + 0.3  # the walker's hips
    leg_len, ankle_z, foot_len = 0.491 * s, 0.039 * s, 0.152 * s
    stride = 0.6
    theta = _stride_angle(stride, leg_len, foot_len, 25)
    hip_z = ankle_z + leg_len * math.cos(theta)
    lead = 1.0 if float(p.get("phase", 0.5)) >= 0 else -1.0
    hip_half = 0.055 * s
    for side in (-1.0, 1.0):
        sgn = lead * side
        hip = np.array([x_w, side * hip_half, hip_z])
        ankle = np.array([x_w + sgn * leg_len * math.sin(theta) - 0.036 * s + 0.03, side * hip_half, ankle_z])
        _standing_leg(parts, s, hip, hip + (ankle - hip) * 0.5 + [0.02 * s, 0, 0], ankle)
    # Torso leaning into the push, head topping the cuboid.
    lean = math.radians(12)
    hip_c = np.array([x_w, 0.0, hip_z])
    up = np.array([math.sin(lean), 0.0, math.cos(lean)])
    shoulder = hip_c + up * 0.288 * s
    depth = 0.11 * s
    parts.add("bottom", ellipsoid(hip_c + [0, 0, 0.01 * s], (depth / 2, 0.09 * s, 0.06 * s)))
    _limb(parts, "top", hip_c + up * 0.04 * s, shoulder, 0.085 * s)
    neck = shoulder + up * 0.05 * s
    _limb(parts, "skin", shoulder, neck, 0.03 * s)
    head_top = np.array([neck[0] + 0.02 * s, 0.0, h])
    _head(parts, head_top, s, p)
    # Handles at the hands: a little ahead of the hips, at about the wrist height of hanging arms.
    grip_x, grip_z = x_w + 0.42, 0.47 * s
    grip_y = min(0.26, w / 2 - 0.05)
    b = 0.19 * s
    for side in (-1.0, 1.0):
        sh = shoulder + [0.0, side * b / 2, 0.0]
        grip = np.array([grip_x, side * grip_y, grip_z])
        elbow = (sh + grip) / 2 + [-0.03 * s, side * 0.02 * s, -0.03 * s]
        _limb(parts, "top", sh, elbow, 0.026 * s)
        _limb(parts, "skin", elbow, grip, 0.022 * s)
    front = l / 2
    if p.get("style") == "cart":
        bed0, bed_z = grip_x + 0.25, 0.5
        parts.add("cargo", box((bed0, -w / 2, bed_z), (front - 0.02, w / 2, bed_z + 0.05)))
        for side in (-1.0, 1.0):  # low side boards
            parts.add("cargo", box((bed0, side * w / 2, bed_z + 0.05), (front - 0.02, side * (w / 2 - 0.03), bed_z + 0.2)))
            _limb(parts, "frame", (grip_x, side * grip_y, grip_z), (bed0 + 0.1, side * grip_y, bed_z), 0.018)
        _limb(parts, "frame", (grip_x, -grip_y, grip_z), (grip_x, grip_y, grip_z), 0.018)
        parts.add("cargo", box((front - 0.04, -w / 2, bed_z), (front, w / 2, bed_z + 0.25)))  # front board
        rw = 0.26
        xc = (bed0 + front) / 2
        for side in (-1.0, 1.0):
            _wheel_pair(parts, xc, side * (w / 2 - 0.06), rw, rw, 0.05)
        _limb(parts, "frame", (front - 0.1, 0.0, bed_z), (front - 0.1, 0.0, 0.02), 0.02)  # stand
        if p.get("load"):
            parts.add("crate", box((bed0 + 0.1, -w / 2 + 0.08, bed_z + 0.05), (front - 0.15, w / 2 - 0.08, bed_z + 0.4)))
    else:
        rw = 0.2
        xw = front - rw
        _wheel_pair(parts, xw, 0.0, rw, rw, 0.08)
        t0, t1 = grip_x + 0.3, front - 0.15  # tray: narrow bottom, flared top
        parts.add("cargo", trapezoid_x(t0 + 0.12, t1 - 0.15, t0, t1, 0.45 * w, w, 0.38, 0.72))
        for side in (-1.0, 1.0):
            _limb(parts, "frame", (grip_x, side * grip_y, grip_z), (xw, side * 0.06, rw), 0.018)
            _limb(parts, "frame", (t0 + 0.2, side * 0.2, 0.4), (t0 + 0.15, side * 0.22, 0.02), 0.018)  # leg
        if p.get("load"):
            parts.add("crate", ellipsoid(((t0 + t1) / 2, 0.0, 0.72), ((t1 - t0) / 2 - 0.05, 0.4 * w, 0.1), 1))
    return parts
