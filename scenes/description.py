"""The scene description: the whole city and everything in it as plain, typed data.

Why plain data: the description is the contract between the generator (layout, placement,
weather) and the renderers (Blender, raster). Nothing here knows about bpy or OpenGL, so a
description can be built, tested, diffed and stored as JSON on any machine, and two backends
can be checked against the same one (Kubric's separation of scene model and renderer).

World frame: x east, y north, z up, metres; the road surface is z = 0. Angles are radians; a
yaw is measured about +z from +x. An object's pose is the contract's object frame (x forward,
y left, z up, origin at the cuboid's centre) placed at `center` and turned by `yaw`.

Serialisation (`to_json` / `from_json`) rounds every float to 1e-6 (micrometres, microradians)
and sorts keys, so the same (seed, preset) gives the same bytes on any machine even where two
libms disagree in the last bit. `canonical()` applies the same rounding to a live object, so
what a backend draws is exactly what the JSON says.
"""

from __future__ import annotations

import dataclasses
import json
import math
import types
import typing
from dataclasses import dataclass, field
from typing import Any

FLOAT_DECIMALS = 6

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]
Color = tuple[float, float, float]
Polygon2 = tuple[Vec2, ...]


# ---------------------------------------------------------------------------------------------
# Materials
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Material:
    """A physically based material (the Principled BSDF subset both backends understand).

    Colours are linear RGB in [0, 1]. `emission_strength` is in Blender's units (W/m^2-ish); the
    raster backend maps it to an emissive factor.
    """

    base_color: Color
    roughness: float = 0.5
    metallic: float = 0.0
    transmission: float = 0.0
    emission_color: Color = (0.0, 0.0, 0.0)
    emission_strength: float = 0.0


# ---------------------------------------------------------------------------------------------
# The static city
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Lane:
    """One lane: its centreline from `start` to `end` in the driving direction."""

    lane_id: str
    kind: str  # "driving" or "parking"
    start: Vec2
    end: Vec2
    width: float

    @property
    def heading(self) -> float:
        return math.atan2(self.end[1] - self.start[1], self.end[0] - self.start[0])

    @property
    def length(self) -> float:
        return math.hypot(self.end[0] - self.start[0], self.end[1] - self.start[1])


@dataclass(frozen=True)
class Road:
    """A straight road from city bound to city bound; `axis` is "x" or "y"."""

    road_id: str
    axis: str
    start: Vec2
    end: Vec2
    width: float  # kerb to kerb
    lanes: tuple[Lane, ...]


@dataclass(frozen=True)
class Intersection:
    intersection_id: str
    center: Vec2
    size: Vec2  # extent along x and y (the two roads' widths)
    traffic_lights: bool


@dataclass(frozen=True)
class Crosswalk:
    """A zebra crossing: a rectangle across a road, stripes parallel to the traffic."""

    crosswalk_id: str
    center: Vec2
    length: float  # across the road (the walking direction)
    width: float  # along the road
    yaw: float  # walking direction
    stripe_width: float
    stripe_gap: float


@dataclass(frozen=True)
class Marking:
    """A painted area on the road (lane divider dash, centre line, stop line, edge line)."""

    kind: str
    center: Vec2
    length: float
    width: float
    yaw: float
    color: str  # "white" or "yellow"


@dataclass(frozen=True)
class Sidewalk:
    """A raised, paved or planted slab (top at `height`) as an oriented rectangle.

    `kind`: "sidewalk" (pedestrians walk here), "plaza", or "lawn" (lot ground around buildings,
    or a grass verge between kerb and footway: ids ending in "_verge").
    `road_yaw` is the direction of the road the sidewalk runs along (pedestrians walk that way).
    """

    sidewalk_id: str
    kind: str
    center: Vec2
    length: float
    width: float
    yaw: float
    height: float
    road_yaw: float = 0.0


@dataclass(frozen=True)
class Facade:
    """Facade parameters; windows are generated from these by the mesh builder."""

    floor_height: float
    window_width: float
    window_height: float
    window_spacing: float  # centre to centre along the facade
    wall: Material
    window: Material
    frame: Material
    lit_fraction: float  # of windows lit at night
    seed: int  # drives which windows are lit: part of the description, so deterministic


@dataclass(frozen=True)
class BuildingPart:
    """A prism: a simple polygon footprint (counter-clockwise) extruded from base_z to top_z."""

    footprint: Polygon2
    base_z: float
    top_z: float
    roof: str = "flat"  # "flat" or "gable" (gable only on rectangles, ridge along the long side)
    roof_height: float = 0.0


@dataclass(frozen=True)
class Building:
    building_id: str
    parts: tuple[BuildingPart, ...]
    facade: Facade
    roof: Material


@dataclass(frozen=True)
class Furniture:
    """Street furniture (not annotated): its bounding cuboid, like an agent's, plus parameters.

    kind: street_light, traffic_light, tree, bin, bench, bollard, hydrant, hedge, planter (and the
    other kinds scenes/assets/props.py builds). A junction's corner poles are street lights with
    ids "<intersection_id>_pole<k>" (rigs/sampling.py mounts cameras on them).
    `params` holds plain data (arm length, trunk height, colours; `clearance`: the height below
    which only the pole or trunk stands). `footprint` is the world polygon of what stands on the
    ground (pole, trunk, bench), the obstacle agents must keep clear of.
    """

    furniture_id: str
    kind: str
    center: Vec3
    dims: Vec3
    yaw: float
    params: dict[str, Any] = field(default_factory=dict)
    footprint: Polygon2 = ()


@dataclass(frozen=True)
class City:
    """The static part of a scene: built once per (seed, preset), reused by every frame."""

    preset: str
    seed: int
    bounds: tuple[float, float, float, float]  # xmin, ymin, xmax, ymax
    curb_height: float
    roads: tuple[Road, ...]
    intersections: tuple[Intersection, ...]
    crosswalks: tuple[Crosswalk, ...]
    markings: tuple[Marking, ...]
    sidewalks: tuple[Sidewalk, ...]
    buildings: tuple[Building, ...]
    furniture: tuple[Furniture, ...]
    road_material: Material
    sidewalk_material: Material
    lawn_material: Material


# ---------------------------------------------------------------------------------------------
# What changes per frame
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class AssetSpec:
    """Which mesh an agent wears: a procedural family with its parameters, or a user file.

    `family` is a fine class name for procedural assets, or "user"; `params` is plain data
    (style, colours, pose) that the family's builder turns into a mesh without any randomness.
    """

    family: str
    params: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Agent:
    """An annotated object: class, cuboid in the world (centre, dims l w h, yaw) and asset."""

    instance_id: int
    category: str
    center: Vec3
    dims: Vec3
    yaw: float
    state: str  # moving, parked, walking, standing, crossing, placed
    asset: AssetSpec

    @property
    def name(self) -> str:
        return agent_name(self.instance_id, self.category)


def agent_name(instance_id: int, category: str) -> str:
    """The object name both backends use, so their objects can be matched by name."""
    return f"agent_{instance_id:04d}_{category}"


@dataclass(frozen=True)
class Weather:
    """kind: clear, overcast, rain, snow, fog.

    fog_density: extinction coefficient in 1/m (meteorological visibility ~ 3.912 / density);
    precipitation: 0..1 intensity; wetness and snow_cover: 0..1 of the ground.
    """

    kind: str
    cloud_cover: float
    fog_density: float
    precipitation: float
    wetness: float
    snow_cover: float
    wind_direction: float  # radians, where precipitation drifts towards

    @property
    def visibility(self) -> float:
        return 3.912 / self.fog_density if self.fog_density > 0 else math.inf


@dataclass(frozen=True)
class Lighting:
    """Time of day and the sun; angles in degrees (as people read them), strengths in Blender units."""

    time_of_day: str  # dawn, morning, noon, afternoon, dusk, night
    hour: float
    day_of_year: int
    latitude: float
    sun_elevation: float  # degrees above the horizon (negative at night)
    sun_azimuth: float  # degrees, clockwise from north (+y) towards east (+x)
    sun_strength: float
    sky_strength: float
    street_lights_on: bool
    vehicle_lights_on: bool
    windows_lit: bool

    @property
    def sun_direction(self) -> Vec3:
        """Unit vector from the ground towards the sun, in the world frame (x east, y north)."""
        el, az = math.radians(self.sun_elevation), math.radians(self.sun_azimuth)
        return (math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el))


@dataclass(frozen=True)
class Scene:
    """One frame's world: the static city, the agents, weather and lighting.

    `dataset_seed` and `frame_index` say which numpy Generator drew the per-frame part:
    np.random.default_rng([dataset_seed, frame_index]). In a sequence (scenes/world.py)
    `frame_index` is the sequence q, whose instant 0 is that frame; `instant` k is the instant,
    `time` its seconds from the sequence's start and `velocities` each agent's world velocity
    (m/s, parallel to `agents`). Their defaults are a legacy frame's and are left out of its JSON
    (_OMITTED_AT_DEFAULT), so a legacy Scene serialises to the same bytes as before they existed.
    """

    city: City
    agents: tuple[Agent, ...]
    weather: Weather
    lighting: Lighting
    dataset_seed: int
    frame_index: int
    instant: int = 0
    time: float = 0.0
    velocities: tuple[Vec3, ...] = ()


# ---------------------------------------------------------------------------------------------
# JSON
# ---------------------------------------------------------------------------------------------


_FIELD_NAMES: dict[type, tuple[str, ...]] = {}
# Fields written only when they differ from these defaults: added after descriptions were stored,
# so descriptions without them keep their bytes (and read back with the defaults).
_OMITTED_AT_DEFAULT: dict[type, dict[str, Any]] = {Scene: {"instant": 0, "time": 0.0, "velocities": ()}}


def _plain(value: Any) -> Any:
    # Exact built-in types first (most values): cheaper than the generic checks below, same result.
    t = type(value)
    if t is float:
        if not math.isfinite(value):
            raise ValueError(f"non-finite float in a scene description: {value}")
        r = round(value, FLOAT_DECIMALS)
        return 0.0 if r == 0 else r  # no "-0.0"
    if t is str or t is int or t is bool or value is None:
        return value
    if t is tuple or t is list:
        return [_plain(v) for v in value]
    if t is dict:
        return {str(k): _plain(v) for k, v in value.items()}
    names = _FIELD_NAMES.get(t)
    if names is None and dataclasses.is_dataclass(value) and not isinstance(value, type):
        names = _FIELD_NAMES[t] = tuple(f.name for f in dataclasses.fields(value))
    if names is not None:
        omitted = _OMITTED_AT_DEFAULT.get(t)
        if omitted is not None:
            return {name: _plain(getattr(value, name)) for name in names
                    if name not in omitted or getattr(value, name) != omitted[name]}
        return {name: _plain(getattr(value, name)) for name in names}
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError(f"non-finite float in a scene description: {value}")
        r = round(value, FLOAT_DECIMALS)
        return 0.0 if r == 0 else r
    if isinstance(value, bool) or value is None or isinstance(value, (int, str)):
        return value
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if hasattr(value, "item"):  # numpy scalar
        return _plain(value.item())
    if hasattr(value, "tolist"):  # numpy array
        return _plain(value.tolist())
    raise TypeError(f"cannot serialise {type(value).__name__} in a scene description")


def to_dict(obj: Any) -> Any:
    """Plain JSON-ready data, floats rounded to FLOAT_DECIMALS."""
    return _plain(obj)


def to_json(obj: Any, indent: int | None = None) -> str:
    """Canonical JSON: sorted keys, rounded floats; byte-identical for equal descriptions."""
    return json.dumps(to_dict(obj), sort_keys=True, indent=indent, separators=(",", ":") if indent is None else None)


_HINTS: dict[type, dict[str, Any]] = {}


def _hints(cls: type) -> dict[str, Any]:
    if cls not in _HINTS:
        _HINTS[cls] = typing.get_type_hints(cls)
    return _HINTS[cls]


_DATACLASS_INFO: dict[type, tuple[dict[str, Any], frozenset[str]]] = {}


def _build(tp: Any, data: Any) -> Any:
    if tp is float:
        return float(data)
    if tp is str or tp is int:
        return data
    if dataclasses.is_dataclass(tp):
        info = _DATACLASS_INFO.get(tp)
        if info is None:  # type hints resolved once per class (they were a third of `canonical`)
            info = _DATACLASS_INFO[tp] = (_hints(tp), frozenset(f.name for f in dataclasses.fields(tp)))
        hints, names = info
        unknown = set(data) - names
        if unknown:
            raise ValueError(f"{tp.__name__}: unknown fields {sorted(unknown)}")
        return tp(**{k: _build(hints[k], v) for k, v in data.items()})
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_build(args[0], v) for v in data)
        return tuple(_build(a, v) for a, v in zip(args, data, strict=True))
    if origin is list:
        return [_build(args[0], v) for v in data]
    if origin is dict:
        return {k: _build(args[1], v) for k, v in data.items()}
    if origin in (typing.Union, types.UnionType):
        return data
    if tp is Any:
        return _freeze(data)
    return data


def _freeze(data: Any) -> Any:
    """Plain data inside `params` dicts: lists become tuples so descriptions stay hashable-ish."""
    if isinstance(data, list):
        return tuple(_freeze(v) for v in data)
    if isinstance(data, dict):
        return {k: _freeze(v) for k, v in data.items()}
    return data


def from_dict(cls: type, data: Any) -> Any:
    return _build(cls, data)


def from_json(cls: type, text: str) -> Any:
    return _build(cls, json.loads(text))


def canonical(obj: Any) -> Any:
    """The object as the JSON describes it (floats rounded): what backends should draw."""
    if type(obj) is Agent and type(obj.asset) is AssetSpec and type(obj.asset.params) is dict:
        return _canonical_agent(obj)
    return from_dict(type(obj), to_dict(obj))


def _canonical_agent(a: Agent) -> Agent:
    """from_dict(Agent, to_dict(a)) without the dict round trip: every frame canonicalises each of
    its hundreds of agents, and the generic path walks the type hints of every value. Field by
    field it does what that round trip does (`_plain`, then `_build` by the field's type), so the
    result is the same object (tests/scenes/test_scene_description.py compares the two)."""
    center, dims = a.center, a.dims
    if type(center) is not tuple or type(dims) is not tuple or len(center) != 3 or len(dims) != 3:
        return from_dict(Agent, to_dict(a))  # arrays (to_dict lists them first) and malformed Vec3s
    asset = a.asset
    return Agent(_plain(a.instance_id), _plain(a.category),
                 (float(_plain(center[0])), float(_plain(center[1])), float(_plain(center[2]))),
                 (float(_plain(dims[0])), float(_plain(dims[1])), float(_plain(dims[2]))),
                 float(_plain(a.yaw)), _plain(a.state),
                 AssetSpec(_plain(asset.family), {str(k): _plain_frozen(v) for k, v in asset.params.items()}))


def _plain_frozen(value: Any) -> Any:
    """_freeze(_plain(value)) in one pass: what an `Any` value (an asset's params) becomes."""
    t = type(value)
    if t is float or t is str or t is int or t is bool or value is None:
        return _plain(value)
    if t is tuple or t is list:
        return tuple(_plain_frozen(v) for v in value)
    if t is dict:
        return {str(k): _plain_frozen(v) for k, v in value.items()}
    return _freeze(_plain(value))
