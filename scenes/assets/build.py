"""From an agent's (family, dims, params) or a furniture item to fitted parts, cached.

Why a cache keyed on the parameters: an agent's mesh is a pure function of its AssetSpec and
dims, so the same parked car in frame 7 and frame 8 costs one build.
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
# One frame's agents (~160 downtown) fit, so a frame never builds an agent twice; more would only
# hold meshes of past frames (agents are redrawn every frame) and grow resident memory.
_CACHE_SIZE = 256


def _cached(key: str, make):
    hit = _CACHE.get(key)
    if hit is not None:
        _CACHE.move_to_end(key)
        return hit
    value = make()
    _CACHE[key] = value
    if len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)
    return value


def agent_parts(asset: AssetSpec, dims) -> tuple[dict[str, trimesh.Trimesh], np.ndarray]:
    """Parts in the object frame, fitted exactly to `dims`, and the design's raw extents.

    User assets are scale-free: their dims are their own extent, so the fit leaves them as loaded.
    """
    key = json.dumps([to_dict(asset), to_dict(tuple(dims))], sort_keys=True)

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
