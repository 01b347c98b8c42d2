"""Scene presets: TOML files that set the distributions a city is drawn from.

A preset is not a scene: it says how big blocks are, how many lanes each road has, how tall the
buildings grow, how many agents of each kind appear and which weather and times of day are
likely. `load_preset("downtown")` reads scenes/presets/downtown.toml; any other string that names
an existing file (or ends in .toml) is read as a path. Every field has a default, and an unknown
key is an error (a typo in a preset should fail loudly, not be ignored).

Ranges are written [min, max] and drawn uniformly unless the field's comment says otherwise.
"""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omnigen.scenes.description import from_dict

PRESET_DIR = Path(__file__).resolve().parent / "presets"
DEFAULT_PRESET = "downtown"

Range = tuple[float, float]
IntRange = tuple[int, int]


@dataclass(frozen=True)
class GridSpec:
    blocks_x: int = 2  # full blocks between roads; a row of edge blocks closes each side
    blocks_y: int = 2
    block_size: Range = (60.0, 80.0)  # kerb to kerb, metres
    edge_depth: Range = (30.0, 40.0)  # depth of the edge blocks beyond the outer roads
    road_lanes_x: tuple[int, ...] = (2,)  # lanes per direction of each road along x (cycled)
    road_lanes_y: tuple[int, ...] = (2,)  # ... along y
    lane_width: float = 3.3
    parking_lanes: bool = True
    parking_width: float = 2.3
    sidewalk_width: Range = (3.5, 5.0)
    curb_height: float = 0.15
    crosswalk_probability: float = 0.9  # per intersection approach
    traffic_light_probability: float = 1.0  # per intersection
    turn_lanes: bool = False  # the inner lane of a 2+ lane approach is a left-turn lane before the stop line
    turn_lane_length: float = 30.0  # metres of solid divider and arrows before the stop line
    verge_width: Range = (0.0, 0.0)  # grass verge between kerb and footway (0: none); trees stand on it
    median_width: float = 0.0  # a raised grass median between the two directions of every road (0: none)
    bike_lane_width: float = 0.0  # a bike lane outside the driving lanes each way (0: none); riders keep to it


@dataclass(frozen=True)
class BuildingSpec:
    height: Range = (15.0, 70.0)
    floor_height: Range = (3.2, 4.0)
    setback: Range = (0.0, 1.0)  # from the sidewalk, on street sides
    side_gap: Range = (0.0, 2.0)  # between neighbouring buildings
    lot_width: Range = (18.0, 35.0)  # lots are split until shorter than a draw from this
    min_footprint: float = 6.0
    footprints: dict[str, float] = field(default_factory=lambda: {"rect": 0.55, "l_shape": 0.25, "tower": 0.2})
    gable_probability: float = 0.0  # rectangular low buildings may get a gable roof
    lot_surface: str = "plaza"  # or "lawn"
    window_spacing: Range = (2.2, 3.5)
    lit_fraction: Range = (0.2, 0.6)
    empty_lot_probability: float = 0.05


@dataclass(frozen=True)
class FurnitureSpec:
    street_light_spacing: float = 28.0  # 0: none
    tree_spacing: float = 14.0  # 0: none
    tree_probability: float = 0.5  # per tree slot
    tree_species: dict[str, float] = field(default_factory=lambda: {"round": 1.0})  # round, conical, columnar, spreading
    bins_per_100m: float = 1.5
    benches_per_100m: float = 1.0
    hydrants_per_100m: float = 0.7
    bollards_per_corner: int = 2
    corner_poles: bool = False  # a street light on every junction corner (where roadside cameras hang)
    hedge_probability: float = 0.0  # per lot street side: a hedge along the lot's front (lawn lots)
    median_hedges: bool = False  # shrub rows along the medians (grid.median_width)
    planters_per_100m: float = 0.0  # planters (shrub boxes) on the footway by the kerb
    signpost_probability: float = 0.0  # per junction approach: a traffic sign at its right kerb
    bus_shelters_per_100m: float = 0.0  # bus shelters at the kerb side of wide footways


@dataclass(frozen=True)
class AgentSpec:
    moving_vehicles: IntRange = (8, 16)
    parked_fraction: Range = (0.3, 0.7)  # of the kerb-side parking slots
    queue_probability: float = 0.0  # per lane approaching a signalised junction: vehicles queued at its stop line
    queue_length: IntRange = (1, 5)  # vehicles in such a queue (drawn from vehicle_mix, on top of moving_vehicles)
    pedestrians: IntRange = (20, 40)
    crossing_fraction: float = 0.2  # of pedestrians drawn on crosswalks
    cyclists: IntRange = (2, 5)
    motorcyclists: IntRange = (1, 3)
    cone_groups: IntRange = (0, 2)  # a line of 3 to 6 cones along a lane edge
    single_cones: IntRange = (0, 0)  # lone cones at a lane's kerb side or in a parking lane
    work_zones: IntRange = (0, 0)  # road works closing a stretch of a lane, ringed by a taper of cones
    junction_works: float = 0.0  # per junction: a ring of cones around a work spot in an approach lane
    tricyclists: IntRange = (0, 0)  # three-wheeled cargo tricycles and rickshaws at the right edge
    barrows: IntRange = (0, 0)  # people pushing hand carts, on footways or at the road's right edge
    trams: IntRange = (0, 0)  # trams in the inner lane of roads with at least tram_min_lanes a direction
    tram_min_lanes: int = 3
    vehicle_mix: dict[str, float] = field(default_factory=lambda: {"car": 0.72, "van": 0.12, "truck": 0.08, "bus": 0.08})
    parked_mix: dict[str, float] = field(default_factory=lambda: {"car": 0.85, "van": 0.12, "truck": 0.03})
    user_assets: str = ""  # folder with assets.toml; relative paths are relative to the preset
    user_asset_probability: float = 0.0  # chance an agent of a class with user assets uses one


@dataclass(frozen=True)
class WeatherSpec:
    kinds: dict[str, float] = field(
        default_factory=lambda: {"clear": 0.4, "overcast": 0.25, "rain": 0.15, "snow": 0.08, "fog": 0.12}
    )


@dataclass(frozen=True)
class LightingSpec:
    times: dict[str, float] = field(
        default_factory=lambda: {"dawn": 0.08, "morning": 0.22, "noon": 0.25, "afternoon": 0.22, "dusk": 0.1, "night": 0.13}
    )
    latitude: float = 45.0  # degrees north; sets how high the sun climbs


@dataclass(frozen=True)
class Preset:
    name: str = "custom"
    description: str = ""
    grid: GridSpec = field(default_factory=GridSpec)
    buildings: BuildingSpec = field(default_factory=BuildingSpec)
    furniture: FurnitureSpec = field(default_factory=FurnitureSpec)
    agents: AgentSpec = field(default_factory=AgentSpec)
    weather: WeatherSpec = field(default_factory=WeatherSpec)
    lighting: LightingSpec = field(default_factory=LightingSpec)
    source: str = ""  # where it was read from (not part of the TOML)


def available_presets() -> list[str]:
    return sorted(p.stem for p in PRESET_DIR.glob("*.toml"))


def load_preset(name_or_path: str | Path = DEFAULT_PRESET) -> Preset:
    """A preset by name (scenes/presets/NAME.toml) or by path."""
    text = str(name_or_path)
    path = Path(text)
    if not (path.suffix == ".toml" or path.exists()):
        path = PRESET_DIR / f"{text}.toml"
        if not path.exists():
            raise ValueError(f"unknown scene preset {text!r}; available: {', '.join(available_presets())} or a .toml path")
    with open(path, "rb") as f:
        data = tomllib.load(f)
    data.setdefault("name", path.stem)
    preset = from_dict(Preset, data)
    preset = dataclasses.replace(preset, source=str(path.resolve()))
    validate(preset)
    return preset


MIX_SEPARATOR = ","


def mix_names(scene: str | Path) -> list[str]:
    """The presets of a mix, "downtown,suburban,arterial,intersection" (names or TOML paths); a
    single name or path is a mix of one. Every name is checked, so a typo fails before a render."""
    text = str(scene)
    if MIX_SEPARATOR not in text or Path(text).exists():
        return [text]
    names = [n.strip() for n in text.split(MIX_SEPARATOR)]
    if any(not n for n in names):
        raise ValueError(f"scene mix {text!r}: an empty name (write NAME,NAME,...)")
    for n in names:
        path = Path(n)
        if not (path.suffix == ".toml" or path.exists()) and not (PRESET_DIR / f"{n}.toml").exists():
            raise ValueError(f"scene mix {text!r}: unknown preset {n!r}; available: {', '.join(available_presets())}")
    return names


def preset_for_seed(scene: str | Path, seed: int) -> str:
    """The one preset a city seed draws from a mix: the (seed mod n)-th name.

    Why round robin and not a random draw: consecutive seeds (validate's cities, a cluster's
    shards of seeds) then cover the mix evenly, and which preset a seed got is obvious from the
    seed; the city itself is still drawn from `city_rng(seed)`."""
    names = mix_names(scene)
    return names[int(seed) % len(names)]


def with_overrides(preset: Preset, overrides: dict[str, Any]) -> Preset:
    """A copy with dotted-key overrides, e.g. {"grid.blocks_x": 1, "agents.pedestrians": (2, 4)}."""
    for key, value in overrides.items():
        section, _, name = key.rpartition(".")
        if section:
            sub = getattr(preset, section)
            if name not in {f.name for f in dataclasses.fields(sub)}:
                raise KeyError(key)
            preset = dataclasses.replace(preset, **{section: dataclasses.replace(sub, **{name: value})})
        else:
            preset = dataclasses.replace(preset, **{name: value})
    validate(preset)
    return preset


def validate(preset: Preset) -> None:
    g = preset.grid
    if g.blocks_x < 1 or g.blocks_y < 1:
        raise ValueError("a city needs at least one block along each axis")
    if not g.road_lanes_x or not g.road_lanes_y or min(g.road_lanes_x + g.road_lanes_y) < 1:
        raise ValueError("every road needs at least one lane per direction")
    for label, dist in (
        ("buildings.footprints", preset.buildings.footprints),
        ("furniture.tree_species", preset.furniture.tree_species),
        ("agents.vehicle_mix", preset.agents.vehicle_mix),
        ("agents.parked_mix", preset.agents.parked_mix),
        ("weather.kinds", preset.weather.kinds),
        ("lighting.times", preset.lighting.times),
    ):
        if not dist or min(dist.values()) < 0 or sum(dist.values()) <= 0:
            raise ValueError(f"{label} must be non-negative weights with a positive sum")
    from omnigen.scenes.weather import TIMES_OF_DAY, WEATHER_KINDS

    if set(preset.weather.kinds) - set(WEATHER_KINDS):
        raise ValueError(f"weather.kinds: unknown kinds {sorted(set(preset.weather.kinds) - set(WEATHER_KINDS))}")
    if set(preset.lighting.times) - set(TIMES_OF_DAY):
        raise ValueError(f"lighting.times: unknown times {sorted(set(preset.lighting.times) - set(TIMES_OF_DAY))}")
    if set(preset.buildings.footprints) - {"rect", "l_shape", "tower"}:
        raise ValueError("buildings.footprints: kinds are rect, l_shape, tower")
    if set(preset.furniture.tree_species) - {"round", "conical", "columnar", "spreading"}:
        raise ValueError("furniture.tree_species: kinds are round, conical, columnar, spreading")
    if preset.buildings.lot_surface not in ("plaza", "lawn"):
        raise ValueError("buildings.lot_surface is plaza or lawn")
    a = preset.agents
    for label in ("moving_vehicles", "pedestrians", "cyclists", "motorcyclists", "cone_groups", "single_cones",
                  "work_zones", "tricyclists", "barrows", "trams"):
        lo, hi = getattr(a, label)
        if not 0 <= lo <= hi:
            raise ValueError(f"agents.{label} must be [min, max] counts with 0 <= min <= max, got {[lo, hi]}")
    if not 0 <= a.queue_probability <= 1 or not 1 <= a.queue_length[0] <= a.queue_length[1]:
        raise ValueError("agents.queue_probability is in [0, 1]; agents.queue_length is [min, max] with 1 <= min <= max")
    if not 0 <= a.junction_works <= 1:
        raise ValueError("agents.junction_works is a probability in [0, 1]")
    if a.tram_min_lanes < 1:
        raise ValueError("agents.tram_min_lanes must be >= 1")
    if g.median_width < 0 or g.bike_lane_width < 0 or 0 < g.bike_lane_width < 1.5:
        raise ValueError("grid.median_width must be >= 0 metres; grid.bike_lane_width 0 or at least 1.5 m (a tricycle's width)")
    if not 0 <= g.verge_width[0] <= g.verge_width[1]:
        raise ValueError("grid.verge_width must be [min, max] metres with 0 <= min <= max")
    f = preset.furniture
    if f.corner_poles and g.sidewalk_width[0] < 3.5:
        raise ValueError("furniture.corner_poles needs sidewalks at least 3.5 m wide (the poles stand 1 m from the kerb)")
    if not 0 <= f.hedge_probability <= 1 or not 0 <= f.signpost_probability <= 1 or min(f.planters_per_100m, f.bus_shelters_per_100m) < 0:
        raise ValueError("furniture.hedge_probability and signpost_probability are in [0, 1], planters_per_100m and bus_shelters_per_100m >= 0")
