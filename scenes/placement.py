"""Agents in the city: vehicles and trams in lanes or parked at the kerb, people (some pushing
barrows) on sidewalks and crosswalks, riders and tricycles near the right edge of the road,
traffic cones singly, in lines and around road works.

Rules (each tested):
- moving vehicles (some queued behind the stop lines of signalised junctions), trams and
  riders sit in a driving lane, heading along it with yaw noise
  (normal, 2 degrees, cut at 6) and a small lateral offset, their turned footprint inside the
  lane; trams in the innermost lanes of wide roads, riders, tricycles and some barrows in the
  bike lanes, or near the outer lane's right edge where there are none;
- parked vehicles sit in the kerb-side parking lanes, nose to tail with 0.8 to 2.5 m gaps, away
  from intersections and crosswalks;
- pedestrians stand or walk on sidewalks (walking along the street) or cross on crosswalks;
  people pushing barrows walk along sidewalks;
- cones stand on the road; a work zone's closed stretch and a junction work spot are obstacles
  once ringed, so nothing else is placed inside them;
- no two annotated cuboids intersect: footprints (all agents stand on the ground, so disjoint
  footprints mean disjoint cuboids) keep 0.1 m apart, tested with shapely;
- nothing stands inside a building or on a pole, trunk, bench, hedge or planter (furniture
  footprints), and
  nothing taller than a lamp arm's or tree crown's clearance stands under it.

A drawn agent that finds no free spot in 40 tries is dropped, so counts can fall short of the
preset's draw in a crowded city; that is logged in the Scene only by the agents present.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import Polygon

from omnigen.scenes.assets.catalog import SIZES, draw_asset
from omnigen.scenes.description import Agent, AssetSpec, City, Intersection, Lane
from omnigen.scenes.preset import AgentSpec
from omnigen.scenes.seeding import choice_index
from omnigen.scenes.shapes import Occupancy, rect_corners, rect_polygon, to_world
from omnigen.scenes.weather import pick

AGENT_GAP = 0.1  # metres between annotated footprints
OBSTACLE_GAP = 0.05
TRIES = 40
JUNCTION_CONES = 0.8  # of single cones, the share placed near a junction
YAW_NOISE = math.radians(2.0)
YAW_NOISE_MAX = math.radians(6.0)


@dataclass
class _World:
    """What placement checks against: agents so far, ground obstacles and overhead ones."""

    agents: Occupancy
    ground: Occupancy
    overhead: list[tuple[Polygon, float]]  # (footprint of a canopy or arm, clearance height)
    overhead_bounds: np.ndarray  # (len(overhead), 4) shapely bounds of each canopy
    overhead_clearance: np.ndarray  # (len(overhead),) the clearances, as in `overhead`
    overhead_tree: shapely.STRtree | None  # over the canopies in `overhead` order (None: no canopy)

    def free(self, poly: Polygon, top: float, bounds: tuple[float, float, float, float] | None = None) -> bool:
        """Whether `poly` (reaching up to `top`) keeps clear of everything; `bounds`: poly.bounds."""
        if bounds is None:
            bounds = poly.bounds
        if self.agents.collides(poly, AGENT_GAP, bounds=bounds) or self.ground.collides(poly, OBSTACLE_GAP, bounds=bounds):
            return False
        if not self.overhead:
            return True
        # Only canopies lower than `top` whose bounding box meets the polygon's can intersect it
        # (the same answer as testing every canopy: the box test is necessary for `intersects`).
        x0, y0, x1, y1 = bounds
        b = self.overhead_bounds
        near = np.nonzero((self.overhead_clearance < top) & (b[:, 0] <= x1) & (b[:, 2] >= x0)
                          & (b[:, 1] <= y1) & (b[:, 3] >= y0))[0]
        return not any(poly.intersects(self.overhead[i][0]) for i in near)

    def free_many(self, polys: np.ndarray, tops: np.ndarray) -> np.ndarray:
        """`free` for an array of polygons at once (each against what is placed, not each other)."""
        ok = ~self.agents.collides_many(polys, AGENT_GAP) & ~self.ground.collides_many(polys, OBSTACLE_GAP)
        if self.overhead_tree is not None and ok.any():
            cand, canopy = self.overhead_tree.query(polys, predicate="intersects")
            low = self.overhead_clearance[canopy] < tops[cand]
            ok[cand[low]] = False
        return ok


@dataclass
class _Static:
    """What placement derives from a city alone, built once per city and shared by its frames
    (a frame's placement only adds to copies): obstacles, canopies and lane-junction geometry."""

    city: City
    ground: Occupancy
    overhead: list[tuple[Polygon, float]]
    overhead_bounds: np.ndarray
    overhead_clearance: np.ndarray
    overhead_tree: shapely.STRtree | None  # free_many's query tree over the canopies, built once per city
    crosses: dict[tuple[int, int], bool]  # (id of a lane, id of an intersection) -> _Placer._crosses
    spans: dict[tuple[int, int], tuple[float, float]]  # the same -> _Placer._span
    crossing_zones: Occupancy  # where parked cars keep out (_Placer.parked)
    junction_zones: Occupancy  # where lone cones keep out (_Placer._clear_of_junctions)
    areas: dict[int, Polygon]  # id of a lane, sidewalk or crosswalk -> its rectangle
    parking_spans: dict[int, list[tuple[float, float]]]  # id of a parking lane -> _Placer.parking_spans


_STATIC: dict[int, _Static] = {}  # id(city) -> its _Static; the entry holds the city, so ids stay unique
_STATIC_SIZE = 4


def _static(city: City) -> _Static:
    hit = _STATIC.get(id(city))
    if hit is not None and hit.city is city:
        return hit
    ground = Occupancy()
    for b in city.buildings:
        for part in b.parts:
            ground.add(Polygon(part.footprint))
    overhead = []
    for f in city.furniture:
        if f.footprint:
            ground.add(Polygon(f.footprint))
        if "clearance" in f.params:
            canopy = rect_polygon(f.center[:2], f.dims[0], f.dims[1], f.yaw)
            overhead.append((canopy, float(f.params["clearance"]) + (f.center[2] - f.dims[2] / 2)))
    bounds = np.array([c.bounds for c, _ in overhead], dtype=np.float64).reshape(-1, 4)
    clearance = np.array([h for _, h in overhead], dtype=np.float64)
    tree = shapely.STRtree([c for c, _ in overhead]) if overhead else None
    ground.freeze()  # every frame's copy queries this tree in free_many (parked rows)
    crossing = Occupancy()  # parked cars keep 6 m clear of intersection boxes and 1.5 m of crosswalks
    for i in city.intersections:
        crossing.add(rect_polygon(i.center, i.size[0] + 12.0, i.size[1] + 12.0, 0.0))
    for c in city.crosswalks:
        crossing.add(rect_polygon(c.center, c.length, c.width + 3.0, c.yaw))
    junction = Occupancy()  # lone cones keep 3 m clear of intersection boxes and 0.5 m of crosswalks
    for i in city.intersections:
        junction.add(rect_polygon(i.center, i.size[0] + 6.0, i.size[1] + 6.0, 0.0))
    for c in city.crosswalks:
        junction.add(rect_polygon(c.center, c.length, c.width + 1.0, c.yaw))
    static = _Static(city, ground, overhead, bounds, clearance, tree, {}, {}, crossing, junction, {}, {})
    _STATIC.pop(id(city), None)
    while len(_STATIC) >= _STATIC_SIZE:
        _STATIC.pop(next(iter(_STATIC)))
    _STATIC[id(city)] = static
    return static


def _world(city: City) -> _World:
    s = _static(city)
    return _World(Occupancy(), s.ground.copy(), s.overhead, s.overhead_bounds, s.overhead_clearance, s.overhead_tree)


class _Placer:
    def __init__(self, city: City, rng: np.random.Generator, user_assets=None, user_probability: float = 0.0) -> None:
        self.city, self.rng = city, rng
        self.static = _static(city)
        self.world = _world(city)
        self.agents: list[Agent] = []
        self.signals: dict[str, bool] = {}  # intersection id -> green_x, as `queues` drew it
        self.user_assets = user_assets or []
        self.user_probability = user_probability
        self.driving = [lane for road in city.roads for lane in road.lanes if lane.kind == "driving"]
        self.parking = [lane for road in city.roads for lane in road.lanes if lane.kind == "parking"]
        self.bike = [lane for road in city.roads for lane in road.lanes if lane.kind == "bike"]
        self.rightmost = [lane for road in city.roads for lane in road.lanes
                          if lane.kind == "driving" and not any(o.kind == "driving" and o.lane_id[:-1] == lane.lane_id[:-1]
                                                                and int(o.lane_id[-1]) > int(lane.lane_id[-1]) for o in road.lanes)]

    def inner_lanes(self, min_lanes: int) -> list[Lane]:
        """The innermost driving lane each way of roads with at least `min_lanes` lanes a
        direction: where trams run when the city has no separate tracks."""
        out = []
        for road in self.city.roads:
            driving = [lane for lane in road.lanes if lane.kind == "driving"]
            if len(driving) >= 2 * min_lanes:
                out += [lane for lane in driving if lane.lane_id.endswith(("/fwd0", "/bwd0"))]
        return out

    # -- drawing assets ---------------------------------------------------------------------

    def asset(self, category: str, state: str = "") -> tuple[tuple[float, float, float], AssetSpec]:
        pool = [a for a in self.user_assets if a.category == category]
        if pool and self.rng.random() < self.user_probability:
            chosen = pool[int(self.rng.integers(len(pool)))]
            return chosen.dims, chosen.spec()
        return draw_asset(self.rng, category, state)

    def try_add(self, category: str, state: str, dims, spec: AssetSpec, xy, yaw: float, ground_z: float,
                inside: Polygon | None = None) -> bool:
        l, w, h = dims
        poly = rect_polygon(xy, l, w, yaw)
        if inside is not None and not inside.contains(poly):
            return False
        bounds = poly.bounds
        if not self.world.free(poly, ground_z + h, bounds):
            return False
        self._keep(category, state, dims, spec, xy, yaw, ground_z, poly, bounds)
        return True

    def _keep(self, category: str, state: str, dims, spec: AssetSpec, xy, yaw: float, ground_z: float,
              poly: Polygon, bounds: tuple[float, float, float, float]) -> None:
        """Record an agent whose footprint `poly` (with its `bounds`) was found free: later ones keep
        clear of it, and it gets the next instance id. The one place try_add and add_many keep one."""
        l, w, h = dims
        self.world.agents.add(poly, bounds=bounds)
        yaw = math.atan2(math.sin(yaw), math.cos(yaw))
        self.agents.append(Agent(len(self.agents) + 1, category, (float(xy[0]), float(xy[1]), ground_z + h / 2.0),
                                 (float(l), float(w), float(h)), float(yaw), state, spec))

    def yaw_noise(self, scale: float = 1.0) -> float:
        # min/max: np.clip's value for a finite draw and these nonzero bounds, without its overhead;
        # the cut scales with the spread (parked and queued: 1 degree, cut at 3; with downtown's
        # full kerbs a 6-degree cut let a parked car stand over 0.06 rad off its kerb in frame 0)
        cut = YAW_NOISE_MAX * scale
        return min(max(float(self.rng.normal(0.0, YAW_NOISE * scale)), -cut), cut)

    def pick_lane(self, lanes: list[Lane]) -> Lane:
        lengths = np.array([lane.length for lane in lanes])
        return lanes[choice_index(self.rng, lengths / lengths.sum())]

    # -- kinds of placement -----------------------------------------------------------------

    def in_lane(self, category: str, lanes: list[Lane], edge: str = "centre") -> bool:
        """A moving vehicle or rider along a lane; `edge` "right" keeps it near the lane's right edge."""
        if not lanes:
            return False
        dims, spec = self.asset(category)
        l, w, _ = dims
        for _ in range(TRIES):
            lane = self.pick_lane(lanes)
            t = float(self.rng.uniform(l / 2 + 1.0, lane.length - l / 2 - 1.0))
            room = max((lane.width - w) / 2.0 - 0.1, 0.0)
            if edge == "right":
                across = -room + float(self.rng.uniform(0.0, min(0.4, room)))
            else:
                across = float(np.clip(self.rng.normal(0.0, 0.15), -room, room))
            xy = to_world(lane.start, lane.heading, t, across)
            # The turned footprint must stay in the lane too: a 12 m bus turned 3 degrees reaches
            # 0.3 m further out at its ends than its centre does.
            if self.try_add(category, "moving", dims, spec, xy, lane.heading + self.yaw_noise(), 0.0, self.lane_area(lane)):
                return True
        return False

    def parked(self, fraction: float, mix: dict[str, float]) -> None:
        """Fill each parking lane nose to tail, leaving gaps near intersections and crosswalks.

        Why in this order: a city centre's kerbs hold hundreds of vehicles a frame, and half the
        slots of a lane lie near a junction or crosswalk. The stretches kept clear are known per
        city (parking_spans), so a slot there is passed over before a vehicle is drawn for it, and
        the rows' footprints are tested against what stands already in one vectorised query
        (add_many) instead of one shapely call each.
        """
        shortest = 0.0 if self.user_probability > 0 else min((SIZES[c].lo[0] for c in mix if c in SIZES), default=0.0)
        row = []
        for lane in self.parking:
            spans = self.parking_spans(lane)
            t = float(self.rng.uniform(0.5, 6.0))
            while t < lane.length - 3.0:
                # Each vehicle keeps 0.5 m (nose and tail) out of the stretches kept clear.
                span = _meets(spans, t - 0.5, t + shortest + 0.5)
                if span is not None:  # not even the shortest vehicle fits here: go past the stretch
                    t = span[1] + 0.5 + float(self.rng.uniform(0.0, 4.0))
                    continue
                if self.rng.random() < fraction:  # a car here; drawn only then (most slots stay empty)
                    category = pick(self.rng, mix)
                    dims, spec = self.asset(category)
                    l, w, _ = dims
                    if t + l > lane.length - 0.5:
                        break
                    if _meets(spans, t - 0.5, t + l + 0.5) is None:
                        across = -(lane.width / 2 - 0.25 - w / 2)  # right side 0.25 m from the kerb
                        xy = to_world(lane.start, lane.heading, t + l / 2, across)
                        row.append((category, dims, spec, xy, lane.heading + self.yaw_noise(0.5)))
                        t += l + float(self.rng.uniform(0.8, 2.5))
                        continue
                t += float(self.rng.uniform(2.0, 6.0))
        self.add_many(row, "parked")

    def add_many(self, items: list, state: str) -> None:
        """try_add for many agents on the ground at once: (category, dims, spec, xy, yaw) each, in
        order; one that meets what stands already, or an earlier item, is left out."""
        if not items:
            return
        corners = np.stack([rect_corners(xy, dims[0], dims[1], yaw) for _, dims, _, xy, yaw in items])
        polys = shapely.polygons(corners)
        ok = self.world.free_many(polys, np.array([dims[2] for _, dims, _, _, _ in items], dtype=np.float64))
        # Items of one call may meet each other (rows of two lanes round a corner): the later goes.
        grown = shapely.buffer(polys, AGENT_GAP, join_style="mitre")
        a, b = shapely.STRtree(polys).query(grown, predicate="intersects")
        for i, j in sorted(zip(a.tolist(), b.tolist())):
            if i < j and ok[i]:
                ok[j] = False
        bounds = shapely.bounds(polys)
        for k in np.nonzero(ok)[0]:
            category, dims, spec, xy, yaw = items[k]
            self._keep(category, state, dims, spec, xy, yaw, 0.0, polys[k], tuple(bounds[k]))

    def parking_spans(self, lane: Lane) -> list[tuple[float, float]]:
        """Where along a parking lane (from its start) its rectangle meets a crossing zone (6 m
        round an intersection box, 1.5 m either side of a crosswalk): sorted, merged stretches,
        cached per city. A vehicle whose stretch of the lane keeps out of them keeps out of the
        zones, since its footprint lies inside the lane's rectangle."""
        hit = self.static.parking_spans.get(id(lane))
        if hit is not None:
            return hit
        area = self.lane_area(lane)
        d = np.array([math.cos(lane.heading), math.sin(lane.heading)])
        spans = []
        for zone in self.static.crossing_zones.polygons:
            meet = area.intersection(zone)
            if not meet.is_empty:
                along = (shapely.get_coordinates(meet) - np.asarray(lane.start, dtype=np.float64)) @ d
                spans.append((float(along.min()), float(along.max())))
        merged: list[tuple[float, float]] = []
        for a, b in sorted(spans):
            if merged and a <= merged[-1][1]:
                merged[-1] = (merged[-1][0], max(merged[-1][1], b))
            else:
                merged.append((a, b))
        self.static.parking_spans[id(lane)] = merged
        return merged

    def pedestrian_on_sidewalk(self, category: str = "pedestrian", walking: bool | None = None) -> bool:
        """A pedestrian (or a person pushing a barrow) walking along the street or standing."""
        strips = [s for s in self.city.sidewalks if s.kind == "sidewalk"]
        if not strips:
            return False
        areas = np.array([s.length * s.width for s in strips])
        if walking is None:
            walking = bool(self.rng.random() < 0.7)
        state = "walking" if walking else "standing"
        dims, spec = self.asset(category, state)
        for _ in range(TRIES):
            s = strips[choice_index(self.rng, areas / areas.sum())]
            along = float(self.rng.uniform(-s.length / 2 + 0.5, s.length / 2 - 0.5))
            across = float(self.rng.uniform(-s.width / 2 + 0.5, s.width / 2 - 0.5)) if s.width > 1.0 else 0.0
            xy = to_world(s.center, s.yaw, along, across)
            if walking:
                yaw = s.road_yaw + (math.pi if self.rng.random() < 0.5 else 0.0) + float(self.rng.normal(0, math.radians(8)))
            else:
                yaw = float(self.rng.uniform(-math.pi, math.pi))
            if self.try_add(category, state, dims, spec, xy, yaw, s.height, self.area(s)):
                return True
        return False

    def pedestrian_on_crosswalk(self) -> bool:
        if not self.city.crosswalks:
            return False
        dims, spec = self.asset("pedestrian", "walking")
        for _ in range(TRIES):
            c = self.city.crosswalks[int(self.rng.integers(len(self.city.crosswalks)))]
            along = float(self.rng.uniform(-c.length / 2 + 0.6, c.length / 2 - 0.6))
            across = float(self.rng.uniform(-c.width / 2 + 0.5, c.width / 2 - 0.5))
            xy = to_world(c.center, c.yaw, along, across)
            yaw = c.yaw + (math.pi if self.rng.random() < 0.5 else 0.0) + float(self.rng.normal(0, math.radians(10)))
            if self.try_add("pedestrian", "crossing", dims, spec, xy, yaw, 0.0, self.area(c)):
                return True
        return False

    def _clear_of_junctions(self, poly: Polygon) -> bool:
        """True when `poly` keeps out of every intersection box (grown by 3 m) and crosswalk."""
        return not self.static.junction_zones.collides(poly)

    def lane_area(self, lane: Lane) -> Polygon:
        """The lane's rectangle (cached per city: every try of every moving agent checks containment)."""
        area = self.static.areas.get(id(lane))
        if area is None:
            area = self.static.areas[id(lane)] = rect_polygon(to_world(lane.start, lane.heading, lane.length / 2.0, 0.0),
                                                              lane.length, lane.width, lane.heading)
        return area

    def area(self, strip) -> Polygon:
        """The rectangle of a sidewalk strip or crosswalk, where people must stand (cached per city)."""
        area = self.static.areas.get(id(strip))
        if area is None:
            area = self.static.areas[id(strip)] = rect_polygon(strip.center, strip.length, strip.width, strip.yaw)
        return area

    def junction_spans(self, lane: Lane) -> list[tuple[float, float]]:
        """The stretches (along the lane, from its start) where it crosses an intersection box."""
        return sorted(self._span(lane, i) for i in self.city.intersections if self._crosses(lane, i))

    def near_junction(self, lane: Lane, lo: float, hi: float) -> float | None:
        """A distance along `lane` between `lo` and `hi` metres before or after one of its junctions
        (where the camera of a pole looks, and where cones mark works and turns), or None."""
        spans = self.junction_spans(lane)
        if not spans:
            return None
        a, b = spans[int(self.rng.integers(len(spans)))]
        gap = float(self.rng.uniform(lo, hi))
        t = b + gap if self.rng.random() < 0.5 else a - gap
        return t if 1.0 < t < lane.length - 1.0 else None

    def single_cone(self) -> bool:
        """A lone cone by the kerb: in a parking lane or at the right edge of the outer driving
        lane; most (JUNCTION_CONES) within 5-20 m of a junction, where works, turns and
        crossings are marked (and where pole cameras look)."""
        lanes = self.parking + self.rightmost
        if not lanes:
            return False
        dims, spec = self.asset("traffic_cone")
        at_junction = bool(self.rng.random() < JUNCTION_CONES)
        for _ in range(TRIES):
            lane = self.pick_lane(lanes)
            t = self.near_junction(lane, 5.0, 20.0) if at_junction else None
            if t is None:
                t = float(self.rng.uniform(1.0, lane.length - 1.0))
            across = -lane.width / 2 + 0.3 + dims[1] / 2 + float(self.rng.uniform(0.0, 0.4))
            xy = to_world(lane.start, lane.heading, t, across)
            if not self._clear_of_junctions(rect_polygon(xy, dims[0], dims[1], 0.0)):
                continue
            if self.try_add("traffic_cone", "placed", dims, spec, xy, float(self.rng.uniform(-math.pi, math.pi)), 0.0):
                return True
        return False

    def work_zone(self) -> bool:
        """Road works closing a stretch of the outer driving lane: a taper of cones leading
        traffic out of the lane, a line along its inner edge, two cones closing its end. The
        closed stretch becomes an obstacle, so no vehicle or person is placed inside it."""
        if not self.rightmost:
            return False
        after_junction = bool(self.rng.random() < 0.5)  # half start just past a junction
        for _ in range(TRIES):
            lane = self.pick_lane(self.rightmost)
            length, taper = float(self.rng.uniform(8.0, 24.0)), float(self.rng.uniform(5.0, 10.0))
            if lane.length < length + taper + 12.0:
                continue
            t0 = float(self.rng.uniform(taper + 4.0, lane.length - length - 4.0))
            if after_junction:
                ends = [b for _, b in self.junction_spans(lane)]
                if ends:
                    t0 = ends[int(self.rng.integers(len(ends)))] + float(self.rng.uniform(6.0, 14.0)) + taper
                    if t0 + length + 4.0 > lane.length:
                        continue
            mid = to_world(lane.start, lane.heading, t0 + (length - taper) / 2.0, 0.0)
            area = rect_polygon(mid, length + taper + 1.0, lane.width, lane.heading)
            if not self._clear_of_junctions(area) or not self.world.free(area, 1.0):
                continue
            half = lane.width / 2.0 - 0.35
            spots = []  # (along, across): the taper from the right edge to the inner edge, ...
            n_taper = max(3, int(math.ceil(taper / 2.0)) + 1)
            for k in range(n_taper):
                f = k / (n_taper - 1)
                spots.append((t0 - taper * (1.0 - f), -half + 2.0 * half * f))
            spacing = float(self.rng.uniform(2.0, 3.5))
            t = t0 + spacing
            while t < t0 + length:  # ... along the inner edge, ...
                spots.append((t, half))
                t += spacing
            for f in (0.5, 0.0):  # ... and across the end, back to the right edge
                spots.append((t0 + length + 0.8, -half + 2.0 * half * f))
            placed = 0
            for along, across in spots:
                dims, spec = self.asset("traffic_cone")
                xy = to_world(lane.start, lane.heading, along, across)
                placed += self.try_add("traffic_cone", "placed", dims, spec, xy, lane.heading + float(self.rng.uniform(-0.3, 0.3)), 0.0)
            inner = rect_polygon(to_world(lane.start, lane.heading, t0 + length / 2.0, -0.3), length - 0.6, lane.width - 1.4, lane.heading)
            self.world.ground.add(inner)
            return placed > 0
        return False

    def junction_works(self, probability: float) -> None:
        """At each junction with `probability`: a ring of 4 to 7 cones around a work spot (an
        open manhole, a repaired patch) in one of the lanes through it, from 10 m inside the
        junction box to 5 m beyond it (crosswalks may be fenced off too): where the junction's
        pole cameras look, near enough for a cone to fill the annotator's 16 pixels at 320 x 240
        (works farther down the approaches were too small to count in 10-frame sets)."""
        for inter in self.city.intersections:
            if self.rng.random() >= probability:
                continue
            lanes = [lane for lane in self.driving if self._crosses(lane, inter)]
            if not lanes:
                continue
            for _ in range(TRIES):
                lane = lanes[int(self.rng.integers(len(lanes)))]
                a, b = self._span(lane, inter)
                gap = float(self.rng.uniform(-min(10.0, (b - a) / 2.0 - 2.0), 5.0))
                t = b + gap if self.rng.random() < 0.5 else a - gap
                radius = float(self.rng.uniform(0.8, 1.4))
                room = lane.width / 2.0 - 0.3
                if not radius + 1.0 < t < lane.length - radius - 1.0:
                    continue
                center = to_world(lane.start, lane.heading, t, float(self.rng.uniform(-0.3, 0.3)))
                spot = rect_polygon(center, 2 * radius + 0.6, min(2 * radius + 0.6, 2 * room + 0.6), lane.heading)
                if not self.world.free(spot, 1.0):
                    continue
                n = int(self.rng.integers(4, 8))
                phase = float(self.rng.uniform(0, 2 * math.pi))
                for k in range(n):
                    ang = phase + 2 * math.pi * k / n
                    along, across = radius * math.cos(ang), float(np.clip(radius * math.sin(ang), -room + 0.3, room - 0.3))
                    dims, spec = self.asset("traffic_cone")
                    xy = to_world(center, lane.heading, along, across)
                    self.try_add("traffic_cone", "placed", dims, spec, xy, float(self.rng.uniform(-math.pi, math.pi)), 0.0)
                self.world.ground.add(rect_polygon(center, max(2 * radius - 0.9, 0.2), max(min(2 * radius, 2 * room - 0.6) - 0.9, 0.2),
                                                   lane.heading))
                break

    def _crosses(self, lane: Lane, inter) -> bool:
        """Whether `lane` runs through the intersection box (cached per city: pure geometry)."""
        key = (id(lane), id(inter))
        hit = self.static.crosses.get(key)
        if hit is None:
            hit = self.static.crosses[key] = lane_crosses(lane, inter)
        return hit

    def _span(self, lane: Lane, inter) -> tuple[float, float]:
        """Where along `lane` it enters and leaves the intersection box (cached per city)."""
        key = (id(lane), id(inter))
        hit = self.static.spans.get(key)
        if hit is None:
            hit = self.static.spans[key] = lane_span(lane, inter)
        return hit

    def queues(self, probability: float, length, mix: dict[str, float]) -> None:
        """Traffic at signalised junctions by the signal's phase: red to one road, green to the
        other. In each lane approaching on the red road, with `probability`, a queue of `length`
        vehicles nose to tail (1.5-3 m apart) behind the stop line and crosswalk, as pole cameras
        see at a red light; each lane of the green road, with `probability`, carries traffic
        through the junction instead (`through`). Why: queues on all four approaches round an
        empty junction box is a junction at all-red; a roadside camera over a real junction sees
        one road waiting and the other's vehicles crossing the box."""
        for inter in self.city.intersections:
            if not inter.traffic_lights:
                continue
            green_x = bool(self.rng.random() < 0.5)  # whether the road along x has green
            self.signals[inter.intersection_id] = green_x  # a moving world's signals start from it
            for lane in self.driving:
                if not self._crosses(lane, inter) or self.rng.random() >= probability:
                    continue
                if (abs(math.cos(lane.heading)) > 0.5) == green_x:
                    self.through(lane, inter, mix)
                    continue
                a, _ = self._span(lane, inter)
                front = a - float(self.rng.uniform(6.5, 7.5))  # behind the widest crosswalk and stop line
                for _ in range(int(self.rng.integers(int(length[0]), int(length[1]) + 1))):
                    category = pick(self.rng, mix)
                    dims, spec = self.asset(category)
                    t = front - dims[0] / 2
                    if t - dims[0] / 2 < 1.0:
                        break
                    xy = to_world(lane.start, lane.heading, t, float(np.clip(self.rng.normal(0.0, 0.1), -0.2, 0.2)))
                    if not self.try_add(category, "moving", dims, spec, xy, lane.heading + self.yaw_noise(0.5), 0.0,
                                        self.lane_area(lane)):
                        break  # something stands in the queue's way: it ends there
                    front = t - dims[0] / 2 - float(self.rng.uniform(1.5, 3.0))

    def through(self, lane: Lane, inter, mix: dict[str, float]) -> None:
        """A lane with green: vehicles from 8 m before the junction box (over the stop line and
        crosswalk) to 12 m past it, crossing the box or entering or leaving it, 8-25 m apart
        (city traffic moving off and through a junction at 20-40 km/h, about 1.5-3 s apart)."""
        a, b = self._span(lane, inter)
        t = a - 8.0 + float(self.rng.uniform(0.0, 12.0))
        while t < b + 12.0:
            category = pick(self.rng, mix)
            dims, spec = self.asset(category)
            mid = t + dims[0] / 2
            if not dims[0] / 2 + 1.0 < mid < lane.length - dims[0] / 2 - 1.0:
                break
            xy = to_world(lane.start, lane.heading, mid, float(np.clip(self.rng.normal(0.0, 0.15), -0.3, 0.3)))
            self.try_add(category, "moving", dims, spec, xy, lane.heading + self.yaw_noise(), 0.0, self.lane_area(lane))
            t += dims[0] + float(self.rng.uniform(8.0, 25.0))

    def cone_line(self) -> None:
        """3 to 6 cones 1.5 to 3 m apart along the right edge of a driving lane (road works)."""
        if not self.rightmost:
            return
        n, gap = int(self.rng.integers(3, 7)), float(self.rng.uniform(1.5, 3.0))
        lane = self.pick_lane(self.rightmost)
        t0 = float(self.rng.uniform(3.0, max(lane.length - 3.0 - n * gap, 3.5)))
        across = -lane.width / 2 + 0.45
        for k in range(n):
            dims, spec = self.asset("traffic_cone")
            xy = to_world(lane.start, lane.heading, t0 + k * gap, across)
            self.try_add("traffic_cone", "placed", dims, spec, xy, lane.heading + float(self.rng.uniform(-0.3, 0.3)), 0.0)


def lane_crosses(lane: Lane, inter: Intersection) -> bool:
    """Whether `lane` runs through the intersection box (pure geometry; placement caches it)."""
    d = np.subtract(lane.end, lane.start) / lane.length
    off = abs(float(np.cross(d, np.subtract(inter.center, lane.start))))
    return bool(off < abs(d[1]) * inter.size[0] / 2 + abs(d[0]) * inter.size[1] / 2)


def lane_span(lane: Lane, inter: Intersection) -> tuple[float, float]:
    """Where along `lane` (from its start) it enters and leaves the intersection box."""
    d = np.subtract(lane.end, lane.start) / lane.length
    t = float(np.dot(np.subtract(inter.center, lane.start), d))
    half = abs(d[0]) * inter.size[0] / 2 + abs(d[1]) * inter.size[1] / 2
    return (t - half, t + half)


def _meets(spans: list[tuple[float, float]], lo: float, hi: float) -> tuple[float, float] | None:
    """The first of the sorted stretches `spans` that meets [lo, hi], or None."""
    for a, b in spans:
        if a > hi:
            return None
        if b >= lo:
            return (a, b)
    return None


@dataclass(frozen=True)
class Placement:
    """A frame's agents and the signal phases its queues were drawn for.

    Why `signals` is kept: a moving world (scenes/world.py) starts its traffic lights from the
    phase the queues were placed by, so the queued road still waits at t = 0. Junctions without
    an entry drew no phase (the preset queues nothing)."""

    agents: tuple[Agent, ...]
    signals: dict[str, bool]  # intersection id -> whether the road along x has green


def place_agents(city: City, spec: AgentSpec, rng: np.random.Generator, user_assets=None) -> tuple[Agent, ...]:
    """All agents of one frame, drawn from `rng`; instance ids 1..N in placement order."""
    return place_world(city, spec, rng, user_assets).agents


def place_world(city: City, spec: AgentSpec, rng: np.random.Generator, user_assets=None) -> Placement:
    """place_agents with the signal phases drawn on the way (the same draws, the same agents)."""
    p = _Placer(city, rng, user_assets, spec.user_asset_probability)
    count = lambda r: int(rng.integers(int(r[0]), int(r[1]) + 1))  # noqa: E731
    # Classes a preset leaves at (0, 0) draw nothing, so adding one leaves other presets' streams.
    optional = lambda r: count(r) if r[1] > 0 else 0  # noqa: E731
    n_cones, n_moving = count(spec.cone_groups), count(spec.moving_vehicles)
    n_cyc, n_moto, n_ped = count(spec.cyclists), count(spec.motorcyclists), count(spec.pedestrians)
    parked_fraction = float(rng.uniform(*spec.parked_fraction))
    n_zones, n_single = optional(spec.work_zones), optional(spec.single_cones)
    n_tram, n_tri, n_barrow = optional(spec.trams), optional(spec.tricyclists), optional(spec.barrows)
    # Big, constrained things first: road works, cones and parked rows, then traffic, then people.
    if spec.junction_works > 0:
        p.junction_works(spec.junction_works)
    for _ in range(n_zones):
        p.work_zone()
    for _ in range(n_cones):
        p.cone_line()
    for _ in range(n_single):
        p.single_cone()
    if p.parking and parked_fraction > 0:
        p.parked(parked_fraction, spec.parked_mix)
    if spec.queue_probability > 0:
        p.queues(spec.queue_probability, spec.queue_length, spec.vehicle_mix)
    tram_lanes = p.inner_lanes(spec.tram_min_lanes)
    for _ in range(n_tram):
        p.in_lane("tram", tram_lanes)
    for _ in range(n_moving):
        p.in_lane(pick(rng, spec.vehicle_mix), p.driving)
    for _ in range(n_moto):
        p.in_lane("motorcyclist", p.driving)
    # Riders keep to the bike lanes where the city has them, else to the outer lane's right edge.
    ride, edge = (p.bike, "centre") if p.bike else (p.rightmost, "right")
    for _ in range(n_tri):
        p.in_lane("tricyclist", ride, edge=edge)
    for _ in range(n_cyc):
        p.in_lane("cyclist", ride, edge=edge)
    n_cross = int(round(n_ped * spec.crossing_fraction))
    for _ in range(n_cross):
        p.pedestrian_on_crosswalk()
    for _ in range(n_ped - n_cross):
        p.pedestrian_on_sidewalk()
    for _ in range(n_barrow):  # on the footway mostly; some pushed along the road's edge
        if rng.random() < 0.7:
            p.pedestrian_on_sidewalk("barrow", walking=True)
        else:
            p.in_lane("barrow", ride, edge=edge)
    return Placement(tuple(p.agents), dict(p.signals))
