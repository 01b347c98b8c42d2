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
- ego: mounted on a car of the world that drives towards the junction (`ego_host`: a moving car
  or van EGO_BEFORE metres before its box in a lane through it, present for the whole sequence,
  the nearest such): the camera stands EGO_MOUNT metres ahead of the car's front, at the centre
  of its width, with the rig's height, pitch, yaw jitter and fov drawn once per sequence, and
  rides the car (`Ride.at`: the car's pose at each instant composed with that fixed mount). The
  car is no obstacle to its own camera and is dropped from its own view's objects (it stands
  behind the camera); the other views see it. Without such a car the ego camera is held in a
  driving lane through the junction, EGO_BEFORE metres before its box, looking along the lane.
A view whose rig has none of these kinds, or a junction without an approach lane for the ego view,
uses the rig's own anchors. Each view is drawn once per sequence from its own stream `view_rng`
(seed, sequence, rig name, occurrence of that name), so the list's order changes no view, and
keeps the rig's placement checks and object count (sampling.sample_camera, redrawn from its
stream) on instant 0.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, replace
from functools import partial

import numpy as np

from omnigen.rigs.rig import Rig, load_rig
from omnigen.rigs.sampling import (EGO_LANE_END, DrawnCamera, Obstacles, _anchor_pose, _in_lane, camera_at,
                                   draw_camera, driving_lanes, make_camera, sample_camera)
from omnigen.scenes.description import Agent, Scene
from omnigen.scenes.seeding import sequence_streams

_VIEW_SPAWN_KEY = 0x0416
AERIAL_REACH = 40.0
"""Metres from the junction's centre to the point under a drone at most."""
AERIAL_CEILING = 60.0
"""Metres a meeting drone flies at most (the rig's range cut there): higher, the junction's cars
are a few pixels at the sizes a cooperative run renders, and few objects are shared with it."""
EGO_BEFORE = (8.0, 50.0)
"""Metres from a held ego camera to the junction's box along its lane."""
EGO_HOST_BEFORE = (8.0, 60.0)
"""Metres from the front of the car an ego camera rides to the junction's box, at instant 0."""
EGO_MOUNT = 0.1
"""Metres from the front of the ego camera's car to the camera, along the car's heading."""
EGO_CATEGORIES = ("car", "van")


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
    along, _ = lanes.coordinates(np.asarray(junction.center, dtype=np.float64))
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



def ego_host(scene0: Scene, last: Scene, junction) -> Agent | None:
    """The car an ego camera rides through a sequence (instant 0 `scene0` to its last instant
    `last`): among the moving cars and vans whose front is EGO_HOST_BEFORE metres before the
    junction's box, in a lane that runs through it and heading along that lane, and still in the
    world at the last instant, the nearest to the box; None when there is none. No draw: the
    choice changes no stream, so nothing else of the sequence changes with it."""
    if junction is None:
        return None
    ways = dict(approaches(scene0.city, junction))
    present = {a.instance_id for a in last.agents}
    cars = [a for a in scene0.agents
            if a.state == "moving" and a.category in EGO_CATEGORIES and a.instance_id in present]
    if not ways or not cars:
        return None
    lanes = driving_lanes(scene0.city)
    xy = np.array([a.center[:2] for a in cars], dtype=np.float64)
    lane = lanes.under(xy, np.array([a.yaw for a in cars]), math.radians(20.0))
    car_along, _ = lanes.coordinates(xy)
    box_along, _ = lanes.coordinates(np.asarray(junction.center, dtype=np.float64))
    best = None
    for i, (a, k) in enumerate(zip(cars, lane)):
        if int(k) not in ways:
            continue
        gap = float(box_along[0, k]) - max(junction.size) / 2 - float(car_along[i, k]) - a.dims[0] / 2
        if EGO_HOST_BEFORE[0] <= gap <= EGO_HOST_BEFORE[1] and (best is None or gap < best[0]):
            best = (gap, a)
    return None if best is None else best[1]


def mount_point(car: Agent) -> np.ndarray:
    """Where an ego camera stands on `car` (x, y): EGO_MOUNT metres ahead of its front, on its axis."""
    ahead = car.dims[0] / 2 + EGO_MOUNT
    return np.array([car.center[0] + ahead * math.cos(car.yaw), car.center[1] + ahead * math.sin(car.yaw)])


def _riding(car: Agent, rig: Rig, scene: Scene, rng: np.random.Generator, width: int, height: int) -> DrawnCamera:
    return camera_at(rig, mount_point(car), car.yaw, "vehicle", rng, width, height)


@dataclass(frozen=True)
class Ride:
    """An ego camera riding car `track` for a sequence: its pose at instant 0 (`cam0`, drawn on
    the car's pose there) fixes the mount (height, pitch, fov, the yaw relative to the car); each
    instant's camera is the car's pose then composed with that mount."""

    cam0: DrawnCamera
    track: int
    yaw: float  # the camera's heading relative to the car's, radians

    def at(self, scene: Scene) -> DrawnCamera:
        """The camera at `scene`'s instant (the car is present all sequence: `ego_host`)."""
        car = next(a for a in scene.agents if a.instance_id == self.track)
        c = self.cam0
        cam = make_camera(mount_point(car), c.camera_height, car.yaw + self.yaw, c.pitch, c.hfov, c.anchor,
                          c.width, c.height)
        return replace(cam, tries=c.tries)


def place_ego_ride(view: View, scene0: Scene, last: Scene, junction, seed: int, sequence: int, width: int,
                   height: int) -> Ride | None:
    """The ego view's ride for a sequence, or None without a car to ride (the camera is then held)."""
    car = ego_host(scene0, last, junction)
    if car is None:
        return None
    rng = view_rng(seed, sequence, view.rig.name, view.occurrence)
    cam = sample_camera(view.rig, scene0, rng, width, height, Obstacles(scene0, skip=frozenset({car.instance_id})),
                        propose=partial(_riding, car))
    return Ride(cam, car.instance_id, math.remainder(cam.yaw - car.yaw, 2 * math.pi))
