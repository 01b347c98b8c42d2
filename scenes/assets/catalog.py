"""Size distributions and appearance parameters of the procedural families (numpy only).

Sizes are those of the tight cuboid of the object as it stands in the street (l along its
heading, w across, h up), in metres, drawn per axis from a normal truncated to [lo, hi] by
rejection. The means and spreads follow published statistics; docs/scenes.md lists the sources:

- car: KITTI's Car boxes average about l 3.9, w 1.6, h 1.5 (compact European fleet, 2011);
  nuScenes' cars about l 4.6, w 1.95, h 1.7 (US/Singapore fleet, 2019); the issue's l 4.2,
  w 1.8, h 1.5 sits between. We draw l 4.3 +- 0.35, w 1.80 +- 0.07, h 1.50 +- 0.10.
- van: l 5.1 +- 0.5, w 1.98 +- 0.08, h 2.15 +- 0.25 (panel vans and minibuses: Sprinter/Transit class).
- truck: l 8.0 +- 1.6, w 2.45 +- 0.06, h 3.3 +- 0.35 (rigid delivery trucks; EU width limit 2.55).
- bus: l 12.0 +- 0.6, w 2.52 +- 0.03, h 3.15 +- 0.12 (standard 12 m city bus; EU width limit 2.55).
- pedestrian: h 1.70 +- 0.09 (adult stature, both sexes pooled); w 0.58 +- 0.05 (shoulder
  breadth about 0.41-0.47 plus swinging arms); l 0.70 +- 0.10 walking (stride), 0.36 +- 0.04 standing.
- cyclist: l 1.75 +- 0.08 (28" city bicycle), w 0.60 +- 0.04 (handlebar), h 1.72 +- 0.07 (rider).
- motorcyclist: l 2.10 +- 0.12, w 0.82 +- 0.06, h 1.55 +- 0.07.
- tram: l 28 +- 5 (18..38), w 2.50 +- 0.08, h 3.50 +- 0.12: low-floor articulated trams (Citadis,
  Combino, Flexity families) are built from about 20 to 45 m in 2-7 sections, 2.30-2.65 m wide and
  about 3.3-3.6 m to the folded pantograph; Karlsruhe's (the KITTI city's) run about 30-37 m.
  Design values from those specifications, not a measured label statistic.
- tricyclist (DAIR-V2X's class: a rider on a three-wheeled cargo tricycle or cycle rickshaw,
  common in Chinese streets): l 2.4 +- 0.3, w 1.10 +- 0.12, h 1.62 +- 0.10. Pedal cargo trikes
  are about 2.0-2.4 m by 0.8-1.0 m, electric cargo tricycles about 2.6-3.0 m by 1.0-1.3 m; the
  height is the seated rider's head. Design values (no public label statistic found).
- barrow (DAIR-V2X's Barrowlist: a person pushing a hand cart or wheelbarrow): l 1.9 +- 0.25
  (a 1.3-1.5 m barrow or cart plus the walker's 0.5 m), w 0.65 +- 0.07 (tray or cart width),
  h 1.70 +- 0.09 (the walker's stature, as for pedestrians). Design values.
- traffic cone: height one of 0.45 / 0.70 / 0.90 m (the standard sizes), +- 2 cm; base 0.52 h.
  `draw_asset` also draws the other traffic-control devices DAIR-V2X labels TrafficCone: a
  banded cone, a barrel (0.58 m across, 0.95-1.05 m tall, like the US channelizing drum) and a
  delineator post on a base (0.40 m base, 1.0-1.15 m).

Colours are linear RGB (what Blender's Principled BSDF takes).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from omnigen.scenes.description import AssetSpec
from omnigen.scenes.seeding import choice_index


@dataclass(frozen=True)
class SizeDist:
    mean: tuple[float, float, float]
    std: tuple[float, float, float]
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]


SIZES: dict[str, SizeDist] = {
    "car": SizeDist((4.30, 1.80, 1.50), (0.35, 0.07, 0.10), (3.50, 1.62, 1.32), (5.20, 1.98, 1.85)),
    "van": SizeDist((5.10, 1.98, 2.15), (0.50, 0.08, 0.25), (4.30, 1.80, 1.80), (6.40, 2.15, 2.75)),
    "truck": SizeDist((8.00, 2.45, 3.30), (1.60, 0.06, 0.35), (5.50, 2.30, 2.60), (11.5, 2.55, 4.00)),
    "bus": SizeDist((12.0, 2.52, 3.15), (0.60, 0.03, 0.12), (10.5, 2.45, 2.90), (13.5, 2.55, 3.45)),
    "pedestrian": SizeDist((0.70, 0.58, 1.70), (0.10, 0.05, 0.09), (0.48, 0.46, 1.50), (0.95, 0.72, 1.95)),
    "pedestrian_standing": SizeDist((0.36, 0.52, 1.70), (0.04, 0.04, 0.09), (0.28, 0.44, 1.50), (0.46, 0.62, 1.95)),
    "cyclist": SizeDist((1.75, 0.60, 1.72), (0.08, 0.04, 0.07), (1.55, 0.50, 1.55), (1.95, 0.70, 1.90)),
    "motorcyclist": SizeDist((2.10, 0.82, 1.55), (0.12, 0.06, 0.07), (1.80, 0.68, 1.38), (2.40, 0.95, 1.72)),
    "tram": SizeDist((28.0, 2.50, 3.50), (5.0, 0.08, 0.12), (18.0, 2.30, 3.20), (38.0, 2.65, 3.90)),
    "tricyclist": SizeDist((2.40, 1.10, 1.62), (0.30, 0.12, 0.10), (1.80, 0.85, 1.40), (3.20, 1.40, 1.95)),
    "barrow": SizeDist((1.90, 0.65, 1.70), (0.25, 0.07, 0.09), (1.40, 0.50, 1.50), (2.50, 0.85, 1.95)),
}
# Traffic-control devices drawn for the traffic_cone family: (share, base diameter, height range).
CONE_STYLES = {"cone": 0.55, "banded": 0.2, "barrel": 0.12, "delineator": 0.13}
CONE_HEIGHTS = {0.45: 0.3, 0.70: 0.5, 0.90: 0.2}
CONE_BASE_RATIO = 0.52

# Car paint shares roughly as surveyed worldwide: white, black, grey and silver dominate.
CAR_PAINTS = (
    ((0.80, 0.80, 0.78), 0.26), ((0.010, 0.010, 0.012), 0.20), ((0.15, 0.15, 0.16), 0.16),
    ((0.50, 0.50, 0.52), 0.12), ((0.02, 0.05, 0.25), 0.10), ((0.40, 0.02, 0.02), 0.08),
    ((0.05, 0.15, 0.05), 0.03), ((0.45, 0.35, 0.20), 0.03), ((0.75, 0.55, 0.02), 0.02),
)
BUS_LIVERIES = ((0.45, 0.02, 0.02), (0.75, 0.55, 0.02), (0.80, 0.80, 0.78), (0.02, 0.12, 0.35), (0.05, 0.25, 0.08))
SKIN_TONES = ((0.62, 0.43, 0.33), (0.50, 0.32, 0.22), (0.35, 0.20, 0.12), (0.20, 0.11, 0.06), (0.11, 0.06, 0.035), (0.68, 0.50, 0.40))
HAIR_COLORS = ((0.02, 0.015, 0.01), (0.08, 0.04, 0.02), (0.25, 0.15, 0.06), (0.45, 0.35, 0.18), (0.30, 0.30, 0.30))
CLOTH_COLORS = (
    (0.02, 0.02, 0.02), (0.03, 0.04, 0.10), (0.25, 0.25, 0.25), (0.60, 0.60, 0.58), (0.35, 0.03, 0.03),
    (0.05, 0.15, 0.30), (0.20, 0.15, 0.08), (0.45, 0.35, 0.20), (0.05, 0.20, 0.08), (0.70, 0.45, 0.05),
)
PROCEDURAL_FAMILIES = ("car", "van", "truck", "bus", "tram", "pedestrian", "cyclist", "motorcyclist", "tricyclist", "barrow",
                       "traffic_cone")
CAR_STYLES = ("sedan", "hatchback", "wagon", "suv", "pickup")
TRAM_LIVERIES = ((0.80, 0.80, 0.78), (0.75, 0.55, 0.02), (0.45, 0.02, 0.02), (0.02, 0.12, 0.35), (0.05, 0.25, 0.08), (0.6, 0.6, 0.62))
CARGO_COLORS = ((0.05, 0.15, 0.35), (0.35, 0.03, 0.03), (0.05, 0.2, 0.08), (0.6, 0.6, 0.58), (0.7, 0.45, 0.05), (0.1, 0.1, 0.1))


def truncated_normal(rng: np.random.Generator, mean, std, lo, hi) -> np.ndarray:
    """Per-axis normal draws redrawn until inside [lo, hi] (exact truncation, deterministic)."""
    # The same draws as the array form (one rng.normal over all axes per round, redrawn axes
    # replaced); the checks in plain floats, which cost less than numpy's per-call overhead here.
    mean, std = np.asarray(mean, dtype=np.float64), np.asarray(std, dtype=np.float64)
    lo, hi = [float(v) for v in lo], [float(v) for v in hi]
    out = rng.normal(mean, std).tolist()
    for _ in range(100):
        bad = [v < a or v > b for v, a, b in zip(out, lo, hi)]
        if not any(bad):
            break
        new = rng.normal(mean, std).tolist()
        out = [n if x else v for v, n, x in zip(out, new, bad)]
    return np.array([min(max(v, a), b) for v, a, b in zip(out, lo, hi)], dtype=np.float64)


def draw_dims(rng: np.random.Generator, family: str, state: str = "") -> tuple[float, float, float]:
    """Dims of one object. For traffic_cone, `state` may name a CONE_STYLES entry (default a cone)."""
    if family == "traffic_cone" and state == "barrel":
        d = 0.58 + float(rng.normal(0, 0.02))
        return (d, d, float(rng.uniform(0.95, 1.05)))
    if family == "traffic_cone" and state == "delineator":
        return (0.40, 0.40, float(rng.uniform(1.0, 1.15)))
    if family == "traffic_cone":
        heights = sorted(CONE_HEIGHTS)
        p = np.array([CONE_HEIGHTS[h] for h in heights])
        h = heights[choice_index(rng, p / p.sum())] + float(rng.normal(0, 0.02))
        base = CONE_BASE_RATIO * h
        return (base, base, h)
    key = "pedestrian_standing" if family == "pedestrian" and state == "standing" else family
    d = SIZES[key]
    l, w, h = truncated_normal(rng, d.mean, d.std, d.lo, d.hi)
    return (float(l), float(w), float(h))


def _color(rng: np.random.Generator, palette, amount: float = 0.1) -> tuple[float, float, float]:
    c = palette[int(rng.integers(len(palette)))]
    u = rng.uniform(-amount, amount, 3).tolist()
    # Scalar arithmetic, same IEEE operations as numpy's c * (1 + u) clipped to [0, 1] (cheaper).
    r, g, b = (min(max(float(ci) * (1.0 + ui), 0.0), 1.0) for ci, ui in zip(c, u))
    return (r, g, b)


def _weighted_color(rng: np.random.Generator, table) -> tuple[float, float, float]:
    p = np.array([w for _, w in table])
    return _color(rng, [table[choice_index(rng, p / p.sum())][0]], 0.06)


def _person(rng: np.random.Generator) -> dict:
    """Appearance shared by pedestrians and riders."""
    return {
        "skin": _color(rng, SKIN_TONES, 0.06),
        "hair": _color(rng, HAIR_COLORS, 0.1),
        "hair_long": bool(rng.random() < 0.35),
        "top": _color(rng, CLOTH_COLORS, 0.15),
        "bottom": _color(rng, CLOTH_COLORS, 0.15),
        "shoes": _color(rng, CLOTH_COLORS[:3], 0.1),
    }


def draw_params(rng: np.random.Generator, family: str, dims: tuple[float, float, float], state: str = "") -> dict:
    """Appearance parameters (plain data) of one asset of `family` with the given dims."""
    l, w, h = dims
    if family == "car":
        return _car(rng, l, h)
    if family == "van":
        return {"style": ("panel", "windowed", "minibus")[int(rng.integers(3))],
                "paint": _weighted_color(rng, CAR_PAINTS[:5]) if rng.random() < 0.5 else (0.8, 0.8, 0.78),
                "paint_roughness": float(rng.uniform(0.2, 0.45)), "wheel_radius": float(rng.uniform(0.33, 0.38)),
                "rear_windows": bool(rng.random() < 0.6), "plate": _plate(rng)}
    if family == "truck":
        return {"style": ("box", "box", "flatbed")[int(rng.integers(3))], "cab": _weighted_color(rng, CAR_PAINTS),
                "cargo": _color(rng, ((0.8, 0.8, 0.78), (0.55, 0.55, 0.55), (0.3, 0.05, 0.02), (0.05, 0.1, 0.3)), 0.1),
                "axles": 3 if l > 9.5 else 2, "wheel_radius": float(rng.uniform(0.48, 0.53)), "cab_length": float(rng.uniform(1.9, 2.4)),
                "plate": _plate(rng)}
    if family == "bus":
        return {"livery": _color(rng, BUS_LIVERIES, 0.06), "stripe": _color(rng, ((0.8, 0.8, 0.78), (0.02, 0.02, 0.02)), 0.05),
                "wheel_radius": float(rng.uniform(0.48, 0.52)), "doors": 3 if l > 11.5 else 2, "plate": _plate(rng)}
    if family == "tram":
        return {"livery": _color(rng, TRAM_LIVERIES, 0.05), "stripe": _color(rng, TRAM_LIVERIES + ((0.02, 0.02, 0.02),), 0.05),
                "sections": int(max(2, min(5, round(l / 9.0))))}
    if family == "tricyclist":
        p = _person(rng)
        p.update({"style": "rickshaw" if rng.random() < 0.3 else "cargo", "frame": _color(rng, CLOTH_COLORS + ((0.6, 0.6, 0.62),), 0.1),
                  "cargo": _color(rng, CARGO_COLORS, 0.1), "helmet": bool(rng.random() < 0.25), "helmet_color": _color(rng, CLOTH_COLORS, 0.1),
                  "crank": float(rng.uniform(0, 2 * math.pi)), "load": bool(rng.random() < 0.5)})
        return p
    if family == "barrow":
        p = _person(rng)
        p.update({"style": "cart" if rng.random() < 0.4 else "wheelbarrow", "frame": _color(rng, ((0.1, 0.1, 0.1), (0.05, 0.15, 0.3), (0.4, 0.05, 0.02)), 0.1),
                  "cargo": _color(rng, CARGO_COLORS, 0.1), "phase": float(rng.uniform(-1.0, 1.0)), "load": bool(rng.random() < 0.5)})
        return p
    if family == "pedestrian":
        p = _person(rng)
        p.update({"phase": float(rng.uniform(-1.0, 1.0)) if state != "standing" else 0.0, "bag": bool(rng.random() < 0.3),
                  "bag_color": _color(rng, CLOTH_COLORS, 0.1), "walking": state != "standing"})
        return p
    if family == "cyclist":
        p = _person(rng)
        p.update({"frame": _color(rng, CLOTH_COLORS + ((0.6, 0.6, 0.62),), 0.1), "helmet": bool(rng.random() < 0.6),
                  "helmet_color": _color(rng, CLOTH_COLORS, 0.1), "crank": float(rng.uniform(0, 2 * math.pi)),
                  "bag": bool(rng.random() < 0.3), "bag_color": _color(rng, CLOTH_COLORS, 0.1)})
        return p
    if family == "motorcyclist":
        p = _person(rng)
        p.update({"body": _weighted_color(rng, CAR_PAINTS), "helmet_color": _color(rng, CLOTH_COLORS, 0.1),
                  "top_box": bool(rng.random() < 0.3), "bag": bool(rng.random() < 0.2), "bag_color": _color(rng, CLOTH_COLORS, 0.1)})
        return p
    if family == "traffic_cone":
        style = state if state in CONE_STYLES else "cone"
        color = _color(rng, ((0.85, 0.18, 0.01), (0.9, 0.35, 0.0)), 0.05)
        return {"style": style, "color": color, "stripes": 1 if h < 0.6 else 2}
    raise ValueError(f"no procedural family {family!r}")


def _plate(rng: np.random.Generator) -> str:
    """Rear plate colour: white (most of Europe and China's small cars: blue, drawn as white) or yellow."""
    return "yellow" if rng.random() < 0.15 else "white"


def _car(rng: np.random.Generator, l: float, h: float) -> dict:
    """A car's body style follows its drawn dims: tall ones are SUVs or pickups, short ones mostly hatchbacks."""
    if h > 1.62:
        style = "pickup" if l > 4.5 and rng.random() < 0.35 else "suv"
    elif l < 4.1:
        style = ("hatchback", "hatchback", "hatchback", "sedan", "wagon")[int(rng.integers(5))]
    else:
        style = ("sedan", "sedan", "wagon", "hatchback")[int(rng.integers(4))]
    paint = _weighted_color(rng, CAR_PAINTS)
    two_tone = bool(rng.random() < 0.1)
    roof = (0.01, 0.01, 0.012) if paint[0] > 0.3 else (0.8, 0.8, 0.78)
    return {"style": style, "paint": paint, "paint_roughness": float(rng.uniform(0.15, 0.4)),
            "paint_metallic": float(rng.uniform(0.0, 0.7)), "wheel_radius": float(np.clip(0.2 * h + rng.uniform(0.0, 0.04), 0.29, 0.38)),
            "rim": _color(rng, ((0.6, 0.6, 0.62), (0.05, 0.05, 0.05), (0.3, 0.3, 0.32)), 0.05),
            "two_tone": two_tone, "stripe": roof if two_tone else paint, "black_pillars": bool(rng.random() < 0.4),
            "black_mirrors": bool(rng.random() < 0.3), "black_arches": bool(rng.random() < 0.15),
            "lamp_style": int(rng.integers(3)), "grille_width": float(rng.uniform(0.35, 0.95)), "plate": _plate(rng),
            "cab_roof": float(rng.uniform(1.0, 1.5))}


def draw_asset(rng: np.random.Generator, family: str, state: str = "") -> tuple[tuple[float, float, float], AssetSpec]:
    """Dims and the asset spec of a new procedural object.

    A traffic_cone's style (cone, banded, barrel, delineator) is drawn here first, unless `state`
    names one, because its dims depend on it.
    """
    if family == "traffic_cone" and state not in CONE_STYLES:
        names = list(CONE_STYLES)
        p = np.array([CONE_STYLES[k] for k in names])
        state = names[choice_index(rng, p / p.sum())]
    dims = draw_dims(rng, family, state)
    return dims, AssetSpec(family, _freeze(draw_params(rng, family, dims, state)))


def _freeze(value):
    t = type(value)
    if t is float or t is bool or t is int or t is str:  # most values: skip the isinstance chain
        return value
    if isinstance(value, dict):
        return {k: _freeze(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return tuple(_freeze(v) for v in value)
    return value
