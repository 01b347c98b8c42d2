"""Where several rigs meet: the views of a cooperative sequence, all aimed at one junction.

`omnigen render --rig ego,pole,drone` renders every instant of one world from each listed rig.
So that most objects are seen by two views or more, sequence q draws one junction (`meeting_junction`,
from the sequence's "meeting" stream) and every view is placed around it:
- infrastructure (pole): the `intersection` anchor at that junction: mounted on a corner's pole
  (corner drawn), heading at the junction's centre, the rig's yaw jitter, height, pitch and fov;
- aerial (drone): over the junction, heading uniform, height and pitch from the rig (the height
  cut at AERIAL_CEILING), standing
  back h / tan(pitch) so that its optical axis meets the junction's centre; where that is more
  than AERIAL_REACH metres the pitch is raised until it is not (still within the rig's range:
  the preset's steepest pitch is 90 degrees);
- ego: in a driving lane that runs through the junction, EGO_BEFORE metres before its box,
  looking along the lane towards it (the `lane` anchor's checks hold it to the lane). The camera
  is held for the sequence: it does not ride a car yet.
A view whose rig has none of these kinds, or a junction without an approach lane for the ego view,
uses the rig's own anchors. Each view is drawn once per sequence from its own stream `view_rng`
(seed, sequence, rig name, occurrence of that name), so the list's order changes no view, and
keeps the rig's placement checks and object count (sampling.sample_camera, redrawn from its
stream) on instant 0.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass
from functools import partial

import numpy as np

from omnigen.rigs.rig import Rig, load_rig
from omnigen.rigs.sampling import (EGO_LANE_END, DrawnCamera, Obstacles, _anchor_pose, _in_lane, camera_at,
                                   draw_camera, driving_lanes, make_camera, sample_camera)
from omnigen.scenes.description import Scene
from omnigen.scenes.seeding import sequence_streams

_VIEW_SPAWN_KEY = 0x0416
AERIAL_REACH = 40.0
"""Metres from the junction's centre to the point under a drone at most."""
AERIAL_CEILING = 60.0
"""Metres a meeting drone flies at most (the rig's range cut there): higher, the junction's cars
are a few pixels at the sizes a cooperative run renders, and few objects are shared with it."""
EGO_BEFORE = (8.0, 50.0)
"""Metres from an ego camera to the junction's box along its lane."""


@dataclass(frozen=True)
class View:
    """One listed rig: its label (the rig's name, `name.2`, `name.3` for repeats: frame ids and
    file names), the rig, and which occurrence of its name it is."""

    label: str
    rig: Rig
    occurrence: int


def parse_rigs(text: str) -> list[str]:
    """'ego,pole,drone' -> the rig names or TOML paths; one line for an empty entry."""
    names = [n.strip() for n in str(text).split(",")]
    if not all(names):
        raise ValueError(f"--rig {text!r}: an empty rig name; list rigs as NAME,NAME,... (e.g. ego,pole,drone)")
    return names


def views_of(text: str) -> list[View]:
    """The views a --rig list renders, each rig loaded (a bad name or file: its one line)."""
    views, seen = [], {}
    for name in parse_rigs(text):
        rig = load_rig(name)
        n = seen[rig.name] = seen.get(rig.name, 0) + 1
        views.append(View(rig.name if n == 1 else f"{rig.name}.{n}", rig, n))
    return views


def view_rng(dataset_seed: int, sequence: int, name: str, occurrence: int) -> np.random.Generator:
    """A view's own stream for a sequence: keyed by its rig's name and occurrence, not its place
    in the list, and apart from rig_rng (another spawn key)."""
    ss = np.random.SeedSequence([int(dataset_seed), int(sequence), int(occurrence)],
                                spawn_key=(_VIEW_SPAWN_KEY, zlib.crc32(name.encode())))
    return np.random.default_rng(ss)


def approaches(city, junction) -> list[tuple[int, float]]:
    """(driving lane index, metres of lane before the junction's box) of the lanes that run
    through the junction's box with room for an ego camera before it."""
    lanes = driving_lanes(city)
    along, across = lanes.coordinates(np.asarray(junction.center, dtype=np.float64))
    half = max(junction.size) / 2
    room = along[0] - half - EGO_LANE_END
    ok = (np.abs(across[0]) <= min(junction.size) / 2) & (room >= EGO_BEFORE[0]) & (along[0] <= lanes.length)
    return [(int(k), float(room[k])) for k in np.nonzero(ok)[0]]


def meeting_junction(scene0: Scene):
    """The junction a sequence's views meet at: among those with an approach lane (else any),
    drawn from the sequence's "meeting" stream."""
    city = scene0.city
    rng = sequence_streams(scene0.dataset_seed, scene0.frame_index)["meeting"]
    pool = [j for j in city.intersections if approaches(city, j)] or list(city.intersections)
    return pool[int(rng.integers(len(pool)))] if pool else None


def _pole(junction, rig: Rig, scene: Scene, rng: np.random.Generator, width: int, height: int) -> DrawnCamera:
    xy, heading, anchor = _anchor_pose(rig, "intersection", scene, rng, junction=junction)
    return camera_at(rig, xy, heading, anchor, rng, width, height)


def _drone(junction, rig: Rig, scene: Scene, rng: np.random.Generator, width: int, height: int) -> DrawnCamera:
    yaw = rng.uniform(-math.pi, math.pi)
    lo, hi = rig.height
    z = rng.uniform(lo, max(lo, min(hi, AERIAL_CEILING)))
    pitch = max(math.radians(rng.uniform(*rig.pitch)), math.atan2(z, AERIAL_REACH))
    hfov = math.radians(rng.uniform(*rig.hfov))
    back = z / math.tan(pitch) if pitch < math.pi / 2 else 0.0
    xy = np.asarray(junction.center, dtype=np.float64) - back * np.array([math.cos(yaw), math.sin(yaw)])
    return make_camera(xy, z, yaw, pitch, hfov, "intersection", width, height)


def _ego(junction, rig: Rig, scene: Scene, rng: np.random.Generator, width: int, height: int) -> DrawnCamera:
    ways = approaches(scene.city, junction)
    if not ways:
        return draw_camera(rig, scene, rng, width, height)
    k, room = ways[int(rng.integers(len(ways)))]
    lanes = driving_lanes(scene.city)
    along, across = lanes.coordinates(np.asarray(junction.center, dtype=np.float64))
    before = rng.uniform(EGO_BEFORE[0], min(EGO_BEFORE[1], room))
    xy = _in_lane(lanes, k, float(along[0, k]) - max(junction.size) / 2 - before, 0.0, rng)
    return camera_at(rig, xy, float(lanes.heading[k]), "lane", rng, width, height)


_PROPOSE = {"infrastructure": _pole, "aerial": _drone, "ego": _ego}


def place_view(view: View, scene0: Scene, junction, seed: int, sequence: int, width: int, height: int,
               obstacles: Obstacles) -> DrawnCamera:
    """A view's camera for a whole sequence, drawn on instant 0 around the junction."""
    rng = view_rng(seed, sequence, view.rig.name, view.occurrence)
    kind = _PROPOSE.get(view.rig.view) if junction is not None else None
    propose = partial(kind, junction) if kind is not None else None
    return sample_camera(view.rig, scene0, rng, width, height, obstacles, propose=propose)

