"""A Scene compiled into render objects: what both backends draw, built once, here.

Each RenderObject has a name, its parts (role -> trimesh in the object's own frame), the
materials of those roles, a 4x4 object-to-world matrix, and for annotated agents the instance id,
the class and the cuboid. Backends translate RenderObjects; they add nothing to the geometry. That
is what makes "both backends build the same objects" checkable and true by construction.

Static geometry (ground, markings, buildings, furniture) depends only on the City and is cached
per City, so re-randomising a frame rebuilds agents only; static materials follow the frame's
weather and lighting and are recomputed (cheaply) every frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import trimesh

from omnigen.scenes.assets.build import agent_parts, furniture_parts, hold_agents
from omnigen.scenes.assets.static import building_parts, footprints, ground_parts, marking_parts
from omnigen.scenes.description import Agent, City, Material, Scene, to_json
from omnigen.scenes.materials import agent_material, building_material, furniture_material, ground_material


@dataclass
class RenderObject:
    name: str
    kind: str  # ground, markings, building, furniture, agent
    parts: dict[str, trimesh.Trimesh]
    matrix_world: np.ndarray
    materials: dict[str, Material] = field(default_factory=dict)
    instance_id: int = 0  # 0: background in the instance mask
    category: str | None = None
    dims: tuple[float, float, float] | None = None  # the annotated cuboid (agents)


@dataclass(frozen=True)
class LightSource:
    """A lamp: a downward spot at `position` (world), `power` in watts (Blender's units)."""

    name: str
    position: tuple[float, float, float]
    color: tuple[float, float, float]
    power: float
    spot_angle: float  # radians, full cone


def pose_matrix(center, yaw: float) -> np.ndarray:
    """Object-to-world 4x4 of the contract's object frame placed at `center`, turned by `yaw`."""
    c, s = math.cos(yaw), math.sin(yaw)
    m = np.eye(4)
    m[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    m[:3, 3] = center
    return m


_STATIC_CACHE: dict[str, tuple[City, list[RenderObject]]] = {}


_LAST_CITY: list = [None, None, None]  # [city, its key, its (buildings, furniture) by id]


def _city_key(city: City) -> str:
    """The cache key of a city; the JSON hash (~0.1 s for downtown) is kept for the last city seen,
    since every frame of a run asks about the same City object."""
    if _LAST_CITY[0] is not city:
        _LAST_CITY[:] = [city, f"{city.preset}:{city.seed}:{hash(to_json(city))}", None]
    return _LAST_CITY[1]


def _by_id(city: City) -> tuple[dict, dict]:
    """The city's buildings and furniture by id (static_materials looked each up linearly)."""
    _city_key(city)
    if _LAST_CITY[2] is None:
        _LAST_CITY[2] = ({b.building_id: b for b in city.buildings}, {f.furniture_id: f for f in city.furniture})
    return _LAST_CITY[2]


def static_objects(city: City) -> list[RenderObject]:
    """The city's geometry (materials not yet resolved), cached per city."""
    key = _city_key(city)
    hit = _STATIC_CACHE.get(key)
    if hit is not None:
        return hit[1]
    out = [
        RenderObject("ground", "ground", ground_parts(city).meshes(), np.eye(4)),
        RenderObject("markings", "markings", marking_parts(city).meshes(), np.eye(4)),
    ]
    neighbours = footprints(city)
    for b in city.buildings:
        out.append(RenderObject(b.building_id, "building", building_parts(b, neighbours).meshes(), np.eye(4)))
    for f in city.furniture:
        out.append(RenderObject(f.furniture_id, "furniture", furniture_parts(f.kind, f.dims, f.params), pose_matrix(f.center, f.yaw)))
    if len(_STATIC_CACHE) > 4:
        _STATIC_CACHE.clear()
    _STATIC_CACHE[key] = (city, out)
    return out


def static_materials(scene: Scene, obj: RenderObject) -> dict[str, Material]:
    city, w, light = scene.city, scene.weather, scene.lighting
    if obj.kind in ("ground", "markings"):
        return {role: ground_material(role, city, w) for role in obj.parts}
    buildings, furniture = _by_id(city)
    if obj.kind == "building":
        b = buildings[obj.name]
        return {role: building_material(role, b, w, light) for role in obj.parts}
    f = furniture[obj.name]
    return {role: furniture_material(role, f, w, light) for role in obj.parts}


def agent_object(agent: Agent, scene: Scene) -> RenderObject:
    parts, _ = agent_parts(agent.asset, agent.dims)
    return RenderObject(
        agent.name, "agent", parts, pose_matrix(agent.center, agent.yaw),
        {role: agent_material(role, agent, scene.lighting) for role in parts},
        agent.instance_id, agent.category, tuple(agent.dims),
    )


# [the frame's Scene, its agents' RenderObjects by index (None until asked for), its static objects]
_LAST_FRAME: list = [None, [], None]


def _frame(scene: Scene) -> list:
    """What is kept of the frame `scene` (a new Scene starts a new frame, letting the last go)."""
    if _LAST_FRAME[0] is not scene:
        _LAST_FRAME[:] = [scene, [None] * len(scene.agents), None]
        hold_agents(len(scene.agents))
    return _LAST_FRAME


def frame_agent(scene: Scene, k: int) -> RenderObject:
    """The k-th agent of `scene` as a RenderObject, built once per frame, not once per user.

    A frame's Scene is one object handed to every backend and camera of the frame, so it keys the
    frame: a Cycles render's Blender scene (compile_scene, all agents) and its GL labels (the
    agents in view), and every camera of the frame (a redrawn camera, the silhouettes) share the
    same objects. Only the last frame is kept (holding its Scene, so the identity test is sound):
    memory holds one frame's agents. The raster alone asks only for the agents in view, so the
    rest are never built."""
    built = _frame(scene)[1]
    if built[k] is None:
        built[k] = agent_object(scene.agents[k], scene)
    return built[k]


def frame_statics(scene: Scene) -> list[RenderObject]:
    """The static objects with the frame's materials (its weather and light), made once per frame
    as frame_agent's agents are: the Blender scene and the raster's material table share them."""
    kept = _frame(scene)
    if kept[2] is None:
        kept[2] = [RenderObject(obj.name, obj.kind, obj.parts, obj.matrix_world, static_materials(scene, obj))
                   for obj in static_objects(scene.city)]
    return kept[2]


def compile_scene(scene: Scene) -> list[RenderObject]:
    """Static objects (with this frame's materials) followed by the agents, as frame_statics and
    frame_agent keep them."""
    return frame_statics(scene) + [frame_agent(scene, k) for k in range(len(scene.agents))]


def lamp_lights(scene: Scene) -> list[LightSource]:
    """Street lamps as spot lights when they are on (night, dusk, dawn, bad weather)."""
    if not scene.lighting.street_lights_on:
        return []
    out = []
    for f in scene.city.furniture:
        if f.kind != "street_light":
            continue
        head = pose_matrix(f.center, f.yaw) @ np.array([f.dims[0] / 2 - 0.3, 0.0, f.dims[2] / 2 - 0.45, 1.0])
        out.append(LightSource(f"{f.furniture_id}_lamp", (float(head[0]), float(head[1]), float(head[2])), (1.0, 0.82, 0.55), 900.0, math.radians(140)))
    return out


def world_box(obj: RenderObject) -> tuple[np.ndarray, np.ndarray, float]:
    """(centre, extents, yaw) of an object's mesh bounds, in the world: what backends report."""
    v = np.vstack([m.vertices for m in obj.parts.values()])
    lo, hi = v.min(axis=0), v.max(axis=0)
    center = obj.matrix_world @ np.append((lo + hi) / 2.0, 1.0)
    return center[:3], hi - lo, math.atan2(obj.matrix_world[1, 0], obj.matrix_world[0, 0])
