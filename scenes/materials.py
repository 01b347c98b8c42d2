"""Materials per part role, resolved from the description, the weather and the lighting.

Why here and not in the backends: both backends must agree on what a "headlight" looks like at
night or how wet asphalt darkens, so the rule is written once, as plain data (Material), and
each backend only translates a Material into its own shader.

Weather on surfaces: wetness darkens a surface (water fills its pores: up to 40% darker) and
makes it glossy (roughness down to 20%); snow cover blends upward-facing surfaces (roads,
sidewalks, lawns, roofs, ground) towards snow white (SNOW_BLEND * snow_cover). The raster shader
undoes that blend on the ground's roles and lays the snow in patches instead, snow_cover of the
area, with wheel tracks cleared (scenes/road_wear.py); Cycles keeps the blend and hides the
surface pattern under it. Night: lit windows, street lamps, vehicle head- and taillights and bus
signs emit; traffic signals always do.

Surfaces: beside its Material, a part's role names a procedural surface pattern (Surface):
asphalt, worn paint, paving with kerb stones, grass, facades with storey bands, window glass,
roofs, foliage, car paint, concrete. Both backends draw them from world position alone, from the
same data (SURFACE_WEIGHTS, noise_table, road_wear.py's map): the raster shader
(scenes/gl_raster.py) and Cycles' surface material (scenes/blender_backend.py), so a surface
looks the same from every camera, every frame and in both backends. Asphalt's
albedo is that of aged asphalt (about 0.077, 1.7 times a fresh surface's 0.045; the shader adds
darker resurfaced stretches and lighter worn ones): roads people drive on are worn grey, not
black; both backends get it from ground_material.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from omnigen.scenes.description import Agent, Building, City, Furniture, Lighting, Material, Weather

SNOW = (0.82, 0.84, 0.88)
SNOW_BLEND = 0.9  # full snow cover takes an upward surface this far towards SNOW (weathered; the raster shader's asphalt too)
AGED_ASPHALT = 1.7  # aged asphalt reflects more than a fresh surface does (about 0.077 vs 0.045)
GROUND_ROLES = ("ground", "road", "sidewalk", "lawn", "marking_white", "marking_yellow")

_FIXED: dict[str, Material] = {
    "marking_white": Material((0.75, 0.75, 0.72), roughness=0.6),
    "marking_yellow": Material((0.75, 0.5, 0.04), roughness=0.6),
    "glass": Material((0.015, 0.018, 0.022), roughness=0.04, metallic=0.3),
    "tyre": Material((0.018, 0.018, 0.018), roughness=0.9),
    "trim": Material((0.025, 0.025, 0.025), roughness=0.55),
    "crate": Material((0.35, 0.22, 0.1), roughness=0.85),
    "seat": Material((0.02, 0.02, 0.02), roughness=0.7),
    "engine": Material((0.12, 0.12, 0.13), roughness=0.35, metallic=0.8),
    "cone_stripe": Material((0.85, 0.85, 0.85), roughness=0.3),
    "cone_base": Material((0.02, 0.02, 0.02), roughness=0.8),
    "plate": Material((0.7, 0.7, 0.66), roughness=0.4),
    "plate_yellow": Material((0.75, 0.55, 0.03), roughness=0.4),
    "sign_white": Material((0.8, 0.8, 0.78), roughness=0.4),
    "sign_red": Material((0.6, 0.03, 0.03), roughness=0.4),
    "sign_blue": Material((0.03, 0.12, 0.5), roughness=0.4),
    "sign_yellow": Material((0.8, 0.6, 0.03), roughness=0.4),
    "concrete": Material((0.4, 0.39, 0.37), roughness=0.9),
    "soil": Material((0.08, 0.05, 0.03), roughness=1.0),
    "metal": Material((0.09, 0.1, 0.1), roughness=0.45, metallic=0.7),
    "bark": Material((0.07, 0.045, 0.03), roughness=0.95),
    "plastic": Material((0.03, 0.12, 0.05), roughness=0.6),
    "wood": Material((0.25, 0.12, 0.05), roughness=0.8),
    "paint_band": Material((0.75, 0.55, 0.02), roughness=0.5),
    "hydrant": Material((0.45, 0.03, 0.02), roughness=0.5),
    "signal": Material((0.02, 0.02, 0.02), roughness=0.6),
    "lamp_red_off": Material((0.08, 0.01, 0.01), roughness=0.2),
    "lamp_amber_off": Material((0.08, 0.05, 0.01), roughness=0.2),
    "lamp_green_off": Material((0.01, 0.06, 0.03), roughness=0.2),
    "lamp_red": Material((0.8, 0.05, 0.02), roughness=0.2, emission_color=(1.0, 0.05, 0.02), emission_strength=8.0),
    "lamp_amber": Material((0.8, 0.5, 0.02), roughness=0.2, emission_color=(1.0, 0.55, 0.05), emission_strength=8.0),
    "lamp_green": Material((0.05, 0.8, 0.3), roughness=0.2, emission_color=(0.1, 1.0, 0.45), emission_strength=8.0),
}


def _rgb(value, default=(0.5, 0.5, 0.5)) -> tuple[float, float, float]:
    v = value if value is not None else default
    return (float(v[0]), float(v[1]), float(v[2]))


def weathered(m: Material, weather: Weather, upward: bool) -> Material:
    """The material wet and/or under snow (snow only on upward-facing surfaces)."""
    wet = float(weather.wetness)
    c = np.asarray(m.base_color) * (1.0 - 0.4 * wet)
    rough = m.roughness * (1.0 - 0.8 * wet)
    if upward and weather.snow_cover > 0:
        k = SNOW_BLEND * float(weather.snow_cover)
        c = c * (1 - k) + np.asarray(SNOW) * k
        rough = rough * (1 - k) + 0.6 * k
    return replace(m, base_color=(float(c[0]), float(c[1]), float(c[2])), roughness=float(max(rough, 0.04)))


def ground_material(role: str, city: City, weather: Weather) -> Material:
    base = {
        "ground": city.lawn_material if any(s.kind == "lawn" for s in city.sidewalks) else city.sidewalk_material,
        "road": city.road_material,
        "sidewalk": city.sidewalk_material,
        "lawn": city.lawn_material,
    }.get(role) or _FIXED[role]
    if role == "road":  # aged asphalt is grey: the city's tint kept at a third
        c = np.asarray(base.base_color) * AGED_ASPHALT
        grey = float(np.dot(c, (0.2126, 0.7152, 0.0722)))
        c = np.clip(grey + (c - grey) / 3.0, 0.0, 1.0)
        base = replace(base, base_color=(float(c[0]), float(c[1]), float(c[2])))
    return weathered(base, weather, upward=True)


def building_material(role: str, b: Building, weather: Weather, lighting: Lighting) -> Material:
    f = b.facade
    if role == "wall":
        return weathered(f.wall, weather, upward=False)
    if role == "roof":
        return weathered(b.roof, weather, upward=True)
    if role == "frame":
        return f.frame
    if role in ("shopfront", "awning"):
        return shop_material(role, f.seed, weather)
    if role == "window_lit" and lighting.windows_lit:
        return replace(f.window, emission_color=(1.0, 0.78, 0.45), emission_strength=2.5)
    return f.window


# A building's shopfront surround and its awnings' fabric (static.py's shopfronts), linear RGB:
# surrounds mostly dark (black or dark-painted timber and metal, dark granite, bronze aluminium),
# some light stone or render; awnings in the dark greens, maroons, navies and blacks of shop
# awnings, a few red, orange, blue or canvas. One of each a building, drawn from its facade's seed.
SHOPFRONT_COLORS = ((0.03, 0.03, 0.03), (0.05, 0.05, 0.055), (0.08, 0.06, 0.045), (0.02, 0.05, 0.04),
                    (0.1, 0.1, 0.1), (0.05, 0.03, 0.025), (0.32, 0.3, 0.27), (0.5, 0.49, 0.46))
AWNING_COLORS = ((0.02, 0.08, 0.04), (0.12, 0.02, 0.02), (0.02, 0.03, 0.1), (0.03, 0.03, 0.03),
                 (0.35, 0.03, 0.02), (0.5, 0.18, 0.03), (0.05, 0.12, 0.35), (0.45, 0.4, 0.3))


@lru_cache(maxsize=4096)
def _shop_colors(seed: int) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """(surround, fabric) of the building whose facade seed is `seed`: a pure function of the seed,
    cached because every frame restyles every shopfront (a generator per call cost more than the rest)."""
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 0x5F0])
    return SHOPFRONT_COLORS[int(rng.integers(len(SHOPFRONT_COLORS)))], AWNING_COLORS[int(rng.integers(len(AWNING_COLORS)))]


def shop_material(role: str, seed: int, weather: Weather) -> Material:
    """The shopfront surround (role "shopfront") or awning fabric ("awning") of the building
    whose facade seed is `seed`; awnings face up, so snow and rain weather them as roofs."""
    surround, fabric = _shop_colors(int(seed))
    if role == "shopfront":
        return Material(surround, roughness=0.45, metallic=0.2)
    return weathered(Material(fabric, roughness=0.9), weather, upward=True)


def furniture_material(role: str, item: Furniture, weather: Weather, lighting: Lighting) -> Material:
    if role == "lamp":
        if lighting.street_lights_on:
            return Material((0.9, 0.85, 0.7), roughness=0.3, emission_color=(1.0, 0.82, 0.55), emission_strength=40.0)
        return Material((0.6, 0.6, 0.58), roughness=0.3)
    if role == "leaves":
        m = Material(_rgb(item.params.get("leaf_color"), (0.06, 0.16, 0.04)), roughness=0.8)
        return weathered(m, weather, upward=True) if weather.snow_cover > 0 else m
    return _FIXED[role]


def agent_material(role: str, agent: Agent, lighting: Lighting) -> Material:
    p = agent.asset.params
    on = lighting.vehicle_lights_on
    if role == "paint":
        return Material(_rgb(p.get("paint") or p.get("livery")), roughness=float(p.get("paint_roughness", 0.3)),
                        metallic=float(p.get("paint_metallic", 0.2)))
    if role in ("cab", "cargo", "body", "stripe", "rim", "frame"):
        default = {"rim": (0.5, 0.5, 0.52), "stripe": (0.8, 0.8, 0.78)}.get(role, (0.5, 0.5, 0.5))
        metallic = 0.8 if role in ("rim", "frame") else 0.2
        return Material(_rgb(p.get(role), default), roughness=0.35, metallic=metallic)
    if role == "headlight":
        return Material((0.9, 0.9, 0.85), roughness=0.1, emission_color=(1.0, 0.95, 0.85), emission_strength=25.0 if on else 0.0)
    if role == "taillight":
        return Material((0.45, 0.01, 0.01), roughness=0.2, emission_color=(1.0, 0.02, 0.01), emission_strength=6.0 if on else 0.0)
    if role == "sign":
        return Material((0.05, 0.05, 0.05), roughness=0.3, emission_color=(1.0, 0.6, 0.1), emission_strength=6.0)
    if role in ("skin", "hair", "top", "bottom", "shoes"):
        return Material(_rgb(p.get(role)), roughness=0.5 if role == "skin" else 0.8)
    if role == "bag":
        return Material(_rgb(p.get("bag_color")), roughness=0.7)
    if role == "helmet":
        return Material(_rgb(p.get("helmet_color")), roughness=0.25)
    if role == "cone":
        return Material(_rgb(p.get("color"), (0.85, 0.18, 0.01)), roughness=0.5)
    if role == "user":
        return Material(_rgb(p.get("color")), roughness=0.5)
    return _FIXED[role]


# ---------------------------------------------------------------------------------------------
# Procedural surfaces (drawn by the raster shader; plain data like Material)
# ---------------------------------------------------------------------------------------------

# Pattern ids as the shader knows them (gl_raster: SURFACE_WEIGHTS rows and _SURFACES_GLSL tests).
PATTERNS = {"plain": 0, "asphalt": 1, "paint": 2, "paving": 3, "grass": 4, "facade": 5, "glass": 6, "roof": 7,
            "foliage": 8, "car_paint": 9, "concrete": 10}


@dataclass(frozen=True)
class Surface:
    """A procedural pattern over a part's Material: which one, and three numbers it reads.

    scale: the pattern's own length in metres (a storey's height for facades and windows, a tile's
    side for paving); variant: in [0, 1), picks a look among a pattern's variants (a facade's band
    lighter or darker, which windows have blinds) so neighbouring buildings differ; spacing: a
    second length (window spacing along a facade).
    """

    pattern: str = "plain"
    scale: float = 1.0
    variant: float = 0.0
    spacing: float = 1.0

    def row(self) -> tuple[float, float, float, float]:
        return (float(PATTERNS[self.pattern]), self.scale, self.variant, self.spacing)


_ROLE_SURFACES = {"road": Surface("asphalt"), "marking_white": Surface("paint"), "marking_yellow": Surface("paint"),
                  "sidewalk": Surface("paving", 0.6), "lawn": Surface("grass"), "leaves": Surface("foliage"),
                  "paint": Surface("car_paint")}


def _variant(seed: int) -> float:
    """A number in [0, 1) from a seed, the same on every machine (no global random state)."""
    return float(np.random.default_rng(seed & 0xFFFFFFFF).random())


def ground_surface(role: str, city: City) -> Surface:
    if role == "ground":
        lawn = any(s.kind == "lawn" for s in city.sidewalks)
        return Surface("grass") if lawn else Surface("concrete", 2.5)
    return _ROLE_SURFACES.get(role, Surface())


def building_surface(role: str, b: Building) -> Surface:
    f = b.facade
    v = _variant(f.seed)
    if role == "wall":
        return Surface("facade", f.floor_height, v, f.window_spacing)
    if role in ("window", "window_lit"):
        return Surface("glass", f.floor_height, v, f.window_spacing)
    if role == "roof":
        return Surface("roof", 1.0, v)
    return Surface()


def furniture_surface(role: str) -> Surface:
    return _ROLE_SURFACES.get(role, Surface()) if role == "leaves" else Surface()


def agent_surface(role: str) -> Surface:
    return Surface("car_paint") if role == "paint" else Surface()


# What each pattern reads of the shared noise and tile terms, materials.PATTERNS order: amplitudes
# of the noise octaves at 0.6, 9 and 0.75 cells a metre and of the 20 m patches (asphalt repairs,
# dry grass); a tile cell's tint amplitude, its joints' darkness and their half width (m). Both
# backends draw surfaces from it: the raster shader (gl_raster.surface_attributes and its per-pattern
# builds) and Cycles' surface material (blender_backend), so a road has the same grain in both.
SURFACE_WEIGHTS = np.array([
    # amp: lo,  hi,   mid,  big    cell: tint, joint, half width
    [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],  # plain
    [0.22, 0.22, 0.2, 1.0, 0.0, 0.0, 0.0],  # asphalt
    [0.0, 0.05, 0.05, 0.0, 0.0, 0.0, 0.0],  # paint
    [0.2, 0.0, 0.06, 0.0, 0.14, 0.45, 0.01],  # paving (kerb stones on its sides)
    [0.4, 0.2, 0.1, 1.0, 0.0, 0.0, 0.0],  # grass
    [0.2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],  # facade
    [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],  # glass
    [0.2, 0.15, 0.0, 1.0, 0.0, 0.0, 0.0],  # roof
    [0.55, 0.3, 0.0, 0.0, 0.0, 0.0, 0.0],  # foliage
    [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],  # car paint
    [0.2, 0.0, 0.05, 0.0, 0.12, 0.4, 0.008],  # concrete
], dtype=np.float32)
NOISE_SIZE = 256  # the value-noise table, cells a side (it repeats)
NOISE_SEED = 26  # fixed: the same surfaces on every machine, every run and in both backends


def noise_table() -> np.ndarray:
    """The surfaces' value-noise table, (NOISE_SIZE, NOISE_SIZE, 2) float32 in [0, 1): a fine
    channel (white noise, one value a cell) and a coarse one (a periodic Gaussian blur, sigma 4
    cells, of another table, ranked back to uniform). Made from NOISE_SEED alone, nothing
    downloaded; sampled bilinearly as a repeating texture, so N(p * f) is noise with f cells a metre."""
    rng = np.random.default_rng(NOISE_SEED)
    fine = rng.random((NOISE_SIZE, NOISE_SIZE))
    k = np.fft.fftfreq(NOISE_SIZE)
    blur = np.exp(-2.0 * (np.pi * 4.0) ** 2 * (k[:, None] ** 2 + k[None, :] ** 2))
    coarse = np.fft.ifft2(np.fft.fft2(rng.random((NOISE_SIZE, NOISE_SIZE))) * blur).real
    coarse = np.argsort(np.argsort(coarse, axis=None, kind="stable"), kind="stable").reshape(coarse.shape) / coarse.size
    return np.ascontiguousarray(np.stack([fine, coarse], axis=-1), dtype=np.float32)


def part_surface(kind: str, role: str, city: City, building: Building | None = None) -> Surface:
    """The procedural surface of a part: an object of `kind` (ground, markings, building,
    furniture, agent), its `role`, and the building it belongs to for kind "building"."""
    if kind in ("ground", "markings"):
        return ground_surface(role, city)
    if kind == "building":
        return building_surface(role, building)
    return agent_surface(role) if kind == "agent" else furniture_surface(role)
