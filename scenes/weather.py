"""Weather and lighting drawn from a preset's distributions (or fixed by the caller).

Weather kinds: clear, overcast, rain, snow, fog. Fog is an extinction coefficient in 1/m, the one
number both backends need (Blender: volume density; raster: transmittance exp(-density * d));
the meteorological visibility is 3.912 / density (the distance at which contrast falls to 2%).
Every weather kind carries some haze so distant buildings fade as they do outdoors.

Time of day is chosen by what a person sees, not by the clock: "dawn" and "dusk" are the hours
when the sun is between 4 degrees below and 8 degrees above the horizon, "night" when it is more
than 12 degrees below, "noon" within 1.5 h of solar noon. The clock hour follows from a simple
solar model (declination and hour angle; solar time, no equation of time), so sun elevation and
azimuth always agree with the latitude and day of the year in the description. At night (and at
dawn and dusk) street lights, windows and vehicle lights come on; vehicles also use their lights
in rain, snow and fog.
"""

from __future__ import annotations

import math

import numpy as np

from omnigen.scenes.description import Lighting, Weather
from omnigen.scenes.seeding import choice_index

WEATHER_KINDS = ("clear", "overcast", "rain", "snow", "fog")
TIMES_OF_DAY = ("dawn", "morning", "noon", "afternoon", "dusk", "night")
FOG_DENSITY_RANGE = (0.0, 1.0)
"""Fog densities (1/m) a caller may fix: 0 is clear air; 1 leaves a visibility of 4 m (3.912 / 1),
past which a street scene shows nothing to label. The drawn ones stay within 0.0001 to 0.012."""
PRECIPITATION_RANGE = (0.0, 1.0)
"""Rain or snow intensity a caller may fix: a fraction of the heaviest the backends draw."""

# (cloud cover, haze/fog density 1/m, precipitation, wetness, snow cover): uniform ranges.
# Haze is thin enough that a drone 40-120 m up sees cars clearly: clear air keeps 95-99% of the
# contrast over 120 m (visibility 10-40 km), overcast 89-96%, rain 70-89%; fog is fog (visibility
# 330 m to 1 km, under the 1 km that defines it) yet still shows a car 100 m away at 30-67%.
_WEATHER_RANGES: dict[str, dict[str, tuple[float, float]]] = {
    "clear": {"cloud": (0.0, 0.3), "fog": (0.0001, 0.0004), "precip": (0.0, 0.0), "wet": (0.0, 0.0), "snow": (0.0, 0.0)},
    "overcast": {"cloud": (0.7, 1.0), "fog": (0.0003, 0.001), "precip": (0.0, 0.0), "wet": (0.0, 0.3), "snow": (0.0, 0.0)},
    "rain": {"cloud": (0.85, 1.0), "fog": (0.001, 0.003), "precip": (0.2, 1.0), "wet": (0.6, 1.0), "snow": (0.0, 0.0)},
    "snow": {"cloud": (0.8, 1.0), "fog": (0.0015, 0.004), "precip": (0.2, 1.0), "wet": (0.2, 0.5), "snow": (0.3, 1.0)},
    "fog": {"cloud": (0.5, 1.0), "fog": (0.004, 0.012), "precip": (0.0, 0.0), "wet": (0.0, 0.4), "snow": (0.0, 0.0)},
}


def pick(rng: np.random.Generator, weights: dict[str, float]) -> str:
    """A key drawn with probability proportional to its weight (keys sorted: order-proof)."""
    keys = sorted(k for k, w in weights.items() if w > 0)
    p = np.array([weights[k] for k in keys], dtype=np.float64)
    return keys[choice_index(rng, p / p.sum())]


def draw_weather(rng: np.random.Generator, kinds: dict[str, float], kind: str | None = None,
                 fog_density: float | None = None, precipitation: float | None = None) -> Weather:
    """Weather of `kind` (drawn from `kinds` when None); the other arguments fix single values."""
    kind = pick(rng, kinds) if kind is None else kind
    if kind not in _WEATHER_RANGES:
        raise ValueError(f"unknown weather {kind!r}; one of {', '.join(WEATHER_KINDS)}")
    r = _WEATHER_RANGES[kind]
    u = lambda key: float(rng.uniform(*r[key]))  # noqa: E731
    cloud, fog, precip, wet, snow = u("cloud"), u("fog"), u("precip"), u("wet"), u("snow")
    wind = float(rng.uniform(0.0, 2 * math.pi))
    if fog_density is not None:
        fog = _fixed("fog density", fog_density, FOG_DENSITY_RANGE)
    if precipitation is not None:
        precip = _fixed("precipitation", precipitation, PRECIPITATION_RANGE)
    return Weather(kind, cloud, fog, precip, wet, snow, wind)


def _fixed(what: str, value: float, bounds: tuple[float, float]) -> float:
    """A value the caller fixed, refused outside `bounds` (NaN too): a precipitation of 5 was
    clamped to 1 without a word, so the frame showed other weather than was asked for."""
    lo, hi = bounds
    if not lo <= value <= hi:
        raise ValueError(f"{what} {value} is outside [{lo:g}, {hi:g}]")
    return float(value)


# ---------------------------------------------------------------------------------------------
# The sun
# ---------------------------------------------------------------------------------------------


def declination(day_of_year: int) -> float:
    """Solar declination in radians (Cooper's approximation)."""
    return math.radians(-23.44) * math.cos(2 * math.pi / 365.0 * (day_of_year + 10))


def solar_position(latitude: float, day_of_year: int, hour: float) -> tuple[float, float]:
    """(elevation, azimuth) in degrees at local solar time `hour`; azimuth clockwise from north."""
    phi, delta = math.radians(latitude), declination(day_of_year)
    h = math.radians(15.0 * (hour - 12.0))
    sin_el = math.sin(phi) * math.sin(delta) + math.cos(phi) * math.cos(delta) * math.cos(h)
    el = math.asin(max(-1.0, min(1.0, sin_el)))
    az_south = math.atan2(math.sin(h), math.cos(h) * math.sin(phi) - math.tan(delta) * math.cos(phi))
    return math.degrees(el), (math.degrees(az_south) + 180.0) % 360.0


def hour_at_elevation(latitude: float, day_of_year: int, elevation: float, morning: bool) -> float:
    """Solar time at which the sun passes `elevation` degrees (clamped to noon or midnight)."""
    phi, delta = math.radians(latitude), declination(day_of_year)
    c = (math.sin(math.radians(elevation)) - math.sin(phi) * math.sin(delta)) / (math.cos(phi) * math.cos(delta))
    h = math.degrees(math.acos(max(-1.0, min(1.0, c)))) / 15.0
    return 12.0 - h if morning else 12.0 + h


def _hour_for(rng: np.random.Generator, time_of_day: str, latitude: float, day: int) -> float:
    at = lambda el, am: hour_at_elevation(latitude, day, el, am)  # noqa: E731
    if time_of_day == "dawn":
        return float(rng.uniform(at(-4.0, True), at(8.0, True)))
    if time_of_day == "dusk":
        return float(rng.uniform(at(8.0, False), at(-4.0, False)))
    if time_of_day == "noon":
        return float(rng.uniform(10.5, 13.5))
    if time_of_day == "morning":
        lo = at(8.0, True)
        return float(rng.uniform(lo, max(lo, 10.5)))
    if time_of_day == "afternoon":
        hi = at(8.0, False)
        return float(rng.uniform(min(hi, 13.5), hi))
    if time_of_day == "night":
        start, end = at(-12.0, False), at(-12.0, True) + 24.0
        if end <= start:  # the sun never gets 12 degrees below (high latitude summer): midnight
            return 0.0
        return float(rng.uniform(start, end) % 24.0)
    raise ValueError(f"unknown time of day {time_of_day!r}; one of {', '.join(TIMES_OF_DAY)}")


def direct_sun(cloud_cover: float) -> float:
    """The fraction of the clear-sky direct sunlight that clouds let through: 1 - cover^2 / 0.75."""
    return float(np.clip(1.0 - cloud_cover * cloud_cover / 0.75, 0.0, 1.0))


def draw_lighting(rng: np.random.Generator, times: dict[str, float], latitude: float, weather: Weather,
                  time_of_day: str | None = None) -> Lighting:
    """Time of day (drawn from `times` unless fixed), the sun, the sky and which lights are on."""
    time_of_day = pick(rng, times) if time_of_day is None else time_of_day
    day = int(rng.integers(45, 321))  # mid-February to mid-November: no polar extremes
    hour = _hour_for(rng, time_of_day, latitude, day)
    elevation, azimuth = solar_position(latitude, day, hour)
    clear_sky = 1.0 - 0.85 * weather.cloud_cover
    # Direct sun fades near the horizon (longer path through the air) and behind clouds: scattered
    # clouds (cover up to 0.3) hide it a little, an overcast deck (0.87 and more) entirely, so
    # overcast light is the sky's alone: soft, no hard shadows.
    sun = 4.0 * float(np.clip(math.sin(math.radians(max(elevation, 0.0))) * 2.5, 0.0, 1.0)) * direct_sun(weather.cloud_cover)
    twilight = float(np.clip((elevation + 12.0) / 16.0, 0.0, 1.0))  # 0 at -12 deg, 1 at +4 deg
    sky = 0.02 + 0.98 * twilight * (0.6 + 0.4 * clear_sky)
    dark = elevation < 4.0
    bad = weather.kind in ("rain", "snow", "fog")
    return Lighting(
        time_of_day=time_of_day,
        hour=hour,
        day_of_year=day,
        latitude=latitude,
        sun_elevation=elevation,
        sun_azimuth=azimuth,
        sun_strength=sun,
        sky_strength=sky,
        street_lights_on=dark or (bad and elevation < 10.0),
        vehicle_lights_on=elevation < 6.0 or bad,
        windows_lit=elevation < 6.0,
    )
