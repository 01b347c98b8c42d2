"""Rig presets: a distribution over camera poses and intrinsics, read from TOML.

    rig = load_rig("drone")              # rigs/presets/drone.toml
    rig = load_rig("my_rigs/mast.toml")  # or a path

Every key is listed in `Rig` with its meaning; unknown keys and bad values are errors that name
the file and the field. Angles in the file are degrees (people write them); `Rig` keeps them so.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omnigen.conventions import VIEWS
from omnigen.record import FRAME_ID_PATTERN

PRESET_DIR = Path(__file__).parent / "presets"
ANCHORS = ("traffic", "lane", "intersection", "roadside", "anywhere")
RESOLUTION_RANGE = (8, 8192)
"""Image widths and heights a rig's `resolution` and `omnigen render --width/--height` accept:
fewer than 8 pixels hold no object worth a label; 8192 a side (67 megapixels) is the most rig
files have ever been allowed."""
NEAR_DISTANCE_MAX = 10.0
"""The most metres a rig's near_distance may say: it is for what blocks the view close by, and every
ray is tested against the geometry within it, at every draw of a pose (a tenth of a second a draw
at 10 m, growing with the square of the reach; rigs/sampling.py's near_share)."""
NAME_MAX_CHARS = 64
"""A rig's name is part of every frame id and file name (`synthetic-<rig>-s<seed>-<index>`): at
most this long, so that the names stay under the file system's 255 bytes with any seed and index."""


class RigError(ValueError):
    def __init__(self, file: str, field_name: str, message: str):
        super().__init__(f"{file}: field '{field_name}': {message}")
        self.file, self.field, self.message = file, field_name, message


@dataclass(frozen=True)
class Rig:
    """A camera distribution (all ranges [lo, hi], uniform).

    anchor: where the camera stands, with weights: `traffic` (in the lane behind one of the
    frame's moving vehicles, 4-30 m back, looking along the lane: a dashcam in traffic),
    `lane` (over a driving lane's centreline, looking along the traffic; both keep the car that
    carries the camera inside its lane, rigs/sampling.py's lane_problem), `intersection` (at a
    corner of an intersection, looking at its centre), `roadside` (at the kerb, looking along the
    road and in towards it), `anywhere` (uniform over the city's bounds, any heading).
    height: metres above the road surface (world z = 0). pitch: degrees below the horizon.
    yaw_jitter: degrees added to the anchor's heading. hfov: horizontal field of view, degrees.
    resolution: default (width, height). min_objects: fewest annotated objects a frame must
    have, else the pose is redrawn (max_tries times, then the last pose is kept and said so).
    near_distance, max_near_share: a pose is redrawn when more than max_near_share of its image
    sees geometry nearer than near_distance metres (its own pole, a signal arm, a crown beside
    it); 0 m: not checked (a dashcam sees its road and the cars beside it close by).
    """

    name: str
    view: str
    anchor: dict[str, float]
    height: tuple[float, float]
    pitch: tuple[float, float]
    yaw_jitter: tuple[float, float]
    hfov: tuple[float, float]
    resolution: tuple[int, int]
    min_objects: int = 1
    max_tries: int = 60
    near_distance: float = 0.0
    max_near_share: float = 0.02
    description: str = ""
    source: str = field(default="", compare=False)


def rig_names() -> list[str]:
    return sorted(p.stem for p in PRESET_DIR.glob("*.toml"))


def load_rig(name_or_path: str | Path) -> Rig:
    """A preset by name (ego, pole, drone) or a TOML file by path."""
    p = Path(name_or_path)
    if p.suffix != ".toml" and not p.exists():
        p = PRESET_DIR / f"{name_or_path}.toml"
        if not p.exists():
            raise ValueError(f"no rig preset {str(name_or_path)!r}; presets: {', '.join(rig_names())}, or a path to a .toml")
    file = str(p)
    try:
        data = tomllib.loads(p.read_text())
    except OSError as exc:
        raise ValueError(f"{file}: cannot read: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{file}: not valid TOML: {exc}") from None
    return rig_from_dict(data, p.stem, file)


def _range(data: dict, key: str, file: str, lo: float, hi: float) -> tuple[float, float]:
    v = data.get(key)
    if v is None:
        raise RigError(file, key, "missing")
    if (not isinstance(v, list) or len(v) != 2
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)):
        raise RigError(file, key, f"expected [lo, hi] numbers, got {v!r}")
    a, b = float(v[0]), float(v[1])
    if a > b:
        raise RigError(file, key, f"lo {a} > hi {b}")
    if a < lo or b > hi:
        raise RigError(file, key, f"{[a, b]} outside [{lo}, {hi}]")
    return a, b


def _int(data: dict, key: str, file: str, default: int, lo: int, hi: int) -> int:
    v = data.get(key, default)
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        raise RigError(file, key, f"expected an integer in [{lo}, {hi}], got {v!r}")
    return v


def _number(data: dict, key: str, file: str, default: float, hi: float) -> float:
    """A finite number in [0, hi] (NaN and infinities fail the range), `default` when the key is absent."""
    v = data.get(key, default)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= v <= hi:
        raise RigError(file, key, f"expected a number in [0, {hi:g}], got {v!r}")
    return float(v)


def _name(data: dict[str, Any], stem: str, file: str) -> str:
    """The rig's name (the file's stem unless the file sets one) as frame ids and file names take
    it, checked here: a name the record refuses (a space, a slash) failed only after the first
    frame's images were written."""
    text = str(data.get("name", stem))
    if len(text) > NAME_MAX_CHARS or not FRAME_ID_PATTERN.match(text):
        said = "" if "name" in data else " (the file's name: set name = \"...\" in it)"
        raise RigError(file, "name", f"{text!r}{said} must be at most {NAME_MAX_CHARS} letters, digits, '.', '_' "
                                     "or '-', the first a letter or digit: it names every frame and file")
    return text


def rig_from_dict(data: dict[str, Any], name: str, file: str = "<rig>") -> Rig:
    known = {"view", "anchor", "height", "pitch", "yaw_jitter", "hfov", "resolution", "min_objects",
             "max_tries", "near_distance", "max_near_share", "description", "name"}
    unknown = sorted(set(data) - known)
    if unknown:
        raise RigError(file, unknown[0], f"unknown key (known: {', '.join(sorted(known))})")
    view = data.get("view")
    if view not in VIEWS:
        raise RigError(file, "view", f"expected one of {', '.join(VIEWS)}, got {view!r}")
    anchor = data.get("anchor")
    if isinstance(anchor, str):
        anchor = {anchor: 1.0}
    if not isinstance(anchor, dict) or not anchor:
        raise RigError(file, "anchor", f"expected a table of weights over {', '.join(ANCHORS)}, got {anchor!r}")
    for k, w in anchor.items():
        if k not in ANCHORS:
            raise RigError(file, f"anchor.{k}", f"unknown anchor (known: {', '.join(ANCHORS)})")
        if isinstance(w, bool) or not isinstance(w, (int, float)) or w < 0:
            raise RigError(file, f"anchor.{k}", f"weight must be a number >= 0, got {w!r}")
    if sum(anchor.values()) <= 0:
        raise RigError(file, "anchor", "weights sum to zero")
    lo, hi = RESOLUTION_RANGE
    res = data.get("resolution")
    if (not isinstance(res, list) or len(res) != 2
            or not all(isinstance(x, int) and not isinstance(x, bool) and lo <= x <= hi for x in res)):
        raise RigError(file, "resolution", f"expected [width, height] integers in [{lo}, {hi}], got {res!r}")
    return Rig(
        name=_name(data, name, file), view=view,
        anchor={k: float(w) for k, w in anchor.items()},
        height=_range(data, "height", file, 0.3, 1000.0),
        pitch=_range(data, "pitch", file, -89.0, 90.0),
        yaw_jitter=_range(data, "yaw_jitter", file, -180.0, 180.0),
        hfov=_range(data, "hfov", file, 5.0, 170.0),
        resolution=(res[0], res[1]),
        min_objects=_int(data, "min_objects", file, 1, 0, 10_000),
        max_tries=_int(data, "max_tries", file, 60, 1, 10_000),
        near_distance=_number(data, "near_distance", file, 0.0, NEAR_DISTANCE_MAX),
        max_near_share=_number(data, "max_near_share", file, 0.02, 1.0),
        description=str(data.get("description", "")),
        source=file,
    )
