"""From an agent's (family, dims, params) or a furniture item to fitted parts, cached.

Why a cache keyed on the parameters: an agent's mesh is a pure function of its AssetSpec and
dims, so an asset asked for twice (by a frame's Blender scene, its GL labels and the camera
sampler; a user asset in every frame) costs one build. How large: hold_agents.
"""

from __future__ import annotations

import json
from collections import OrderedDict

import numpy as np
import trimesh

from omnigen.scenes.assets import people, props, vehicles
from omnigen.scenes.assets.parts import fit_to_dims
from omnigen.scenes.assets.user import user_parts
from omnigen.scenes.description import AssetSpec, to_dict

AGENT_BUILDERS = {
    "car": vehicles.car,
    "van": vehicles.van,
    "truck": vehicles.truck,
    "bus": vehicles.bus,
    "pedestrian": people.pedestrian,
    "cyclist": people.cyclist,
    "motorcyclist": people.motorcyclist,
    "tricyclist": people.tricyclist,
    "barrow": people.barrow,
    "tram": vehicles.tram,
    "traffic_cone": props.traffic_cone,
}

_CACHE: OrderedDict[str, tuple[dict[str, trimesh.Trimesh], np.ndarray]] = OrderedDict()
_CACHE_MIN = 256  # entries the cache holds whatever the frames (a city's furniture kinds, small presets' agents)
_cache_size = [_CACHE_MIN]


def hold_agents(agents: int) -> None:
    """Let the cache hold a frame of `agents` agents: its size is the most agents a frame has had
    (at least _CACHE_MIN), grown here when a frame brings more (scenes/meshes.py frame_agent).

    Why this bound: a procedural agent's dims and parameters are drawn anew every frame (none of
    downtown's ~400 agents of one frame recurs in the next), so meshes of past frames are never
    asked for again and a larger cache would only hold them and grow resident memory; a smaller
    one than a frame (the fixed 256 against downtown's ~400) evicted a frame's early agents before
    the frame's other users (the raster's labels, the camera sampler's near-geometry test) asked
    for them, and each was built again. Sized to the largest frame, every agent is built once per
    frame, an asset that does recur (a user asset, whose dims are its own) stays, being touched
    every frame, and memory holds at most max(_CACHE_MIN, the largest frame's agents) meshes."""
    _cache_size[0] = max(_cache_size[0], int(agents))


def _cached(key: str, make):
    hit = _CACHE.get(key)
    if hit is not None:
        _CACHE.move_to_end(key)
        return hit
    value = make()
    _CACHE[key] = value
    _trim()
    return value


def _trim() -> None:
    """Evict the least recently used entries beyond the cache's size (hold_agents)."""
    while len(_CACHE) > _cache_size[0]:
        _CACHE.popitem(last=False)


_ADOPTED: dict[int, tuple[AssetSpec, tuple, str]] = {}
"""id(asset) -> (asset, dims, key) of the agents the last adopt_agents brought: the keys their
worker made, so that agent_parts does not make each agent's JSON key again (what most of
compiling a Cycles frame's agents cost: bench_render.py --profile). The asset is held, so its id
stays its own."""


def _agent_key(asset: AssetSpec, dims) -> str:
    known = _ADOPTED.get(id(asset))
    if known is not None and known[0] is asset and known[1] == tuple(dims):
        return known[2]
    return json.dumps([to_dict(asset), to_dict(tuple(dims))], sort_keys=True)


def built_agents(agents) -> list[tuple[str, tuple]]:
    """(cache key, agent_parts) of each of `agents` (scenes.description.Agent): what a process
    that drew a frame (scenes/generate.py FramesAhead's worker) hands the renderer with it, for
    adopt_agents. The parts are bare arrays (parts.Piece), so they cross a pipe as they are."""
    hold_agents(len(agents))
    return [(_agent_key(a.asset, a.dims), agent_parts(a.asset, a.dims)) for a in agents]


def adopt_agents(built: list[tuple[str, tuple]], agents=None) -> None:
    """Put built_agents' meshes in this process's cache, so agent_parts finds them (the same
    arrays, to the byte: a mesh is a pure function of its key); a key already held is kept.
    `agents`, those built_agents was given (as this process holds them), have their keys known
    from then on (_ADOPTED), until the next adoption."""
    hold_agents(len(built))
    _ADOPTED.clear()
    if agents is not None:
        _ADOPTED.update({id(a.asset): (a.asset, tuple(a.dims), key) for a, (key, _) in zip(agents, built, strict=True)})
    for key, value in built:
        if key in _CACHE:
            _CACHE.move_to_end(key)
        else:
            _CACHE[key] = value
    _trim()


def agent_parts(asset: AssetSpec, dims) -> tuple[dict[str, trimesh.Trimesh], np.ndarray]:
    """Parts in the object frame, fitted exactly to `dims`, and the design's raw extents.

    User assets are scale-free: their dims are their own extent, so the fit leaves them as loaded.
    """
    key = _agent_key(asset, dims)

    def make():
        if asset.family == "user":
            meshes = user_parts(asset.params)
        else:
            builder = AGENT_BUILDERS.get(asset.family)
            if builder is None:
                raise ValueError(f"no asset builder for family {asset.family!r}")
            meshes = builder(tuple(float(d) for d in dims), asset.params).meshes()
        return fit_to_dims(meshes, dims)

    return _cached(key, make)


def furniture_parts(kind: str, dims, params: dict) -> dict[str, trimesh.Trimesh]:
    """Parts of a furniture item of `kind` (props.FURNITURE_BUILDERS) fitted exactly to `dims`."""
    if kind not in props.FURNITURE_BUILDERS:
        raise ValueError(f"no furniture builder for kind {kind!r} (known: {', '.join(sorted(props.FURNITURE_BUILDERS))})")
    key = json.dumps(["furniture", kind, to_dict(tuple(dims)), to_dict(params)], sort_keys=True)

    def make():
        meshes = props.FURNITURE_BUILDERS[kind](tuple(float(d) for d in dims), params).meshes()
        return fit_to_dims(meshes, dims)

    return _cached(key, make)[0]
