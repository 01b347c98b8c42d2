"""User assets: a folder of glTF/GLB/OBJ/PLY/STL meshes named by a small TOML.

    # assets.toml, in the folder with the meshes
    [[asset]]
    file = "my_sedan.glb"
    class = "car"          # a fine class (omnigen.conventions.FINE_CLASSES)
    forward = "+x"         # the file's axis that points to the object's front
    up = "+y"              # the file's up axis (glTF files are +y up; many OBJ exports too)
    scale = 1.0            # optional: file units to metres (0.01 for centimetres)
    color = [0.5, 0.5, 0.5]  # optional: base colour (linear RGB); file materials are not read

Loading re-orients the mesh into the contract's object frame (x forward, y left, z up) and
centres it on its bounding box. It is scale-free: the object keeps its own size (times `scale`)
and its cuboid is its extent, rather than being stretched to a class's size distribution, so a
user's asset is rendered as modelled.
"""

from __future__ import annotations

import functools
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from omnigen.conventions import FINE_CLASSES
from omnigen.scenes.description import AssetSpec

AXES = {"+x": (1, 0, 0), "-x": (-1, 0, 0), "+y": (0, 1, 0), "-y": (0, -1, 0), "+z": (0, 0, 1), "-z": (0, 0, -1)}
MESH_SUFFIXES = (".glb", ".gltf", ".obj", ".ply", ".stl", ".off")


@dataclass(frozen=True)
class UserAsset:
    file: str  # absolute path
    category: str
    forward: str
    up: str
    scale: float
    color: tuple[float, float, float]
    dims: tuple[float, float, float]

    def spec(self) -> AssetSpec:
        return AssetSpec("user", {"file": self.file, "forward": self.forward, "up": self.up, "scale": self.scale,
                                  "color": self.color, "category": self.category})


def file_to_object_rotation(forward: str, up: str) -> np.ndarray:
    """3x3 R with object = R @ file: rows are the file's forward, left and up axes."""
    if forward not in AXES or up not in AXES:
        raise ValueError(f"axes must be one of {sorted(AXES)}; got forward={forward!r} up={up!r}")
    f, u = np.array(AXES[forward], float), np.array(AXES[up], float)
    if abs(float(f @ u)) > 0:
        raise ValueError(f"forward {forward} and up {up} must be perpendicular")
    left = np.cross(u, f)
    return np.stack([f, left, u])


@functools.lru_cache(maxsize=64)
def load_oriented(file: str, forward: str, up: str, scale: float) -> trimesh.Trimesh:
    """The file's geometry in the object frame, centred on its bounding box, in metres."""
    mesh = trimesh.load(file, force="mesh", process=False)
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"{file}: no triangles found")
    r = file_to_object_rotation(forward, up)
    v = np.asarray(mesh.vertices, dtype=np.float64) * float(scale) @ r.T
    lo, hi = v.min(axis=0), v.max(axis=0)
    return trimesh.Trimesh(vertices=v - (lo + hi) / 2.0, faces=np.asarray(mesh.faces), process=False)


def load_library(folder: str | Path) -> list[UserAsset]:
    """Every asset listed in FOLDER/assets.toml, loaded once to measure its cuboid."""
    folder = Path(folder).resolve()
    index = folder / "assets.toml"
    if not index.exists():
        raise FileNotFoundError(f"{index} not found: a user asset folder needs an assets.toml")
    with open(index, "rb") as f:
        data = tomllib.load(f)
    out = []
    for i, entry in enumerate(data.get("asset", [])):
        unknown = set(entry) - {"file", "class", "forward", "up", "scale", "color"}
        if unknown:
            raise ValueError(f"{index}: asset {i}: unknown keys {sorted(unknown)}")
        category = entry.get("class", "")
        if category not in FINE_CLASSES:
            raise ValueError(f"{index}: asset {i}: class {category!r} is not a fine class ({', '.join(FINE_CLASSES)})")
        path = (folder / entry["file"]).resolve()
        if path.suffix.lower() not in MESH_SUFFIXES:
            raise ValueError(f"{index}: asset {i}: {path.name} is not one of {', '.join(MESH_SUFFIXES)}")
        forward, up, scale = entry.get("forward", "+x"), entry.get("up", "+z"), float(entry.get("scale", 1.0))
        mesh = load_oriented(str(path), forward, up, scale)
        ext = mesh.extents
        color = tuple(float(c) for c in entry.get("color", (0.5, 0.5, 0.5)))
        out.append(UserAsset(str(path), category, forward, up, scale, color, (float(ext[0]), float(ext[1]), float(ext[2]))))
    return out


def user_parts(params: dict) -> dict[str, trimesh.Trimesh]:
    return {"user": load_oriented(params["file"], params["forward"], params["up"], float(params["scale"]))}
