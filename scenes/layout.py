"""The static city: road grid, intersections, lanes, markings, crosswalks, sidewalks, buildings,
street furniture, drawn from a preset with `city_rng(seed)`.

The city is a grid: `blocks_x` x `blocks_y` full blocks separated by straight roads that run from
bound to bound, closed on every side by a row of edge blocks so that no camera looks into a void.
Every road side facing a block has a sidewalk (raised by the kerb height); the rest of a block is
lot ground (plaza or lawn) split into lots by guillotine cuts, each lot holding one building
(rectangle, L-shape or podium with tower; gable roofs for houses). Traffic drives on the right.

Why a grid of straight roads: lanes, parking slots, crosswalks and traffic lights all follow from
a few numbers, placement can test "is this inside a lane" exactly, and cameras (issue 6) can
stand on lanes or at intersections without searching geometry.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from shapely.geometry import Polygon, box

from omnigen.scenes.description import (
    Building,
    BuildingPart,
    City,
    Crosswalk,
    Facade,
    Furniture,
    Intersection,
    Lane,
    Marking,
    Material,
    Road,
    Sidewalk,
    canonical,
)
from omnigen.scenes.preset import Preset
from omnigen.scenes.seeding import city_rng
from omnigen.scenes.shapes import Occupancy, polygon_tuple, rect_polygon, to_world
from omnigen.scenes.weather import pick

# Facade colours (linear RGB) people see in cities: concrete, render, brick, sandstone, dark stone.
WALL_COLORS = (
    (0.36, 0.35, 0.33), (0.55, 0.50, 0.42), (0.62, 0.61, 0.58), (0.33, 0.12, 0.07), (0.22, 0.09, 0.05),
    (0.48, 0.37, 0.22), (0.12, 0.12, 0.13), (0.45, 0.42, 0.36), (0.30, 0.26, 0.22), (0.58, 0.45, 0.32),
)
HOUSE_COLORS = (
    (0.70, 0.66, 0.55), (0.55, 0.62, 0.66), (0.72, 0.70, 0.66), (0.60, 0.45, 0.30), (0.50, 0.55, 0.42),
    (0.66, 0.54, 0.42), (0.40, 0.22, 0.14),
)
ROOF_COLORS = ((0.08, 0.08, 0.09), (0.20, 0.20, 0.19), (0.25, 0.08, 0.05), (0.12, 0.10, 0.09))


def jitter(rng: np.random.Generator, color: tuple[float, float, float], amount: float = 0.08) -> tuple[float, float, float]:
    c = np.clip(np.asarray(color) * (1.0 + rng.uniform(-amount, amount, 3)), 0.0, 1.0)
    return (float(c[0]), float(c[1]), float(c[2]))


@dataclass
class _Rect:
    x0: float
    y0: float
    x1: float
    y1: float

    @property
    def w(self) -> float:
        return self.x1 - self.x0

    @property
    def h(self) -> float:
        return self.y1 - self.y0


def _axis_positions(rng: np.random.Generator, n_roads: int, road_widths: list[float], block_size, edge_depth) -> tuple[list[float], float]:
    """Road centre positions along one axis (city centred later) and the axis' total length."""
    cursor = float(rng.uniform(*edge_depth))
    centers = []
    for i in range(n_roads):
        centers.append(cursor + road_widths[i] / 2.0)
        cursor += road_widths[i]
        if i < n_roads - 1:
            cursor += float(rng.uniform(*block_size))
    total = cursor + float(rng.uniform(*edge_depth))
    return centers, total


def _road_width(lanes: int, grid) -> float:
    return (2 * lanes * grid.lane_width + (2 * grid.parking_width if grid.parking_lanes else 0.0) + grid.median_width
            + 2 * grid.bike_lane_width)


def build_city(preset: Preset, seed: int) -> City:
    """The static city for (preset, seed); same inputs, same city, byte for byte."""
    rng = city_rng(seed)
    g = preset.grid
    n_yroads, n_xroads = g.blocks_x + 1, g.blocks_y + 1  # roads along y sit at x positions
    lanes_y = [g.road_lanes_y[i % len(g.road_lanes_y)] for i in range(n_yroads)]
    lanes_x = [g.road_lanes_x[j % len(g.road_lanes_x)] for j in range(n_xroads)]
    width_y = [_road_width(n, g) for n in lanes_y]
    width_x = [_road_width(n, g) for n in lanes_x]
    xs, total_x = _axis_positions(rng, n_yroads, width_y, g.block_size, g.edge_depth)
    ys, total_y = _axis_positions(rng, n_xroads, width_x, g.block_size, g.edge_depth)
    xs = [x - total_x / 2.0 for x in xs]
    ys = [y - total_y / 2.0 for y in ys]
    bounds = (-total_x / 2.0, -total_y / 2.0, total_x / 2.0, total_y / 2.0)
    sw_y = [float(rng.uniform(*g.sidewalk_width)) for _ in range(n_yroads)]
    sw_x = [float(rng.uniform(*g.sidewalk_width)) for _ in range(n_xroads)]

    roads: list[Road] = []
    for j, y in enumerate(ys):
        roads.append(_make_road(f"road_x{j}", "x", (bounds[0], y), (bounds[2], y), lanes_x[j], g))
    for i, x in enumerate(xs):
        roads.append(_make_road(f"road_y{i}", "y", (x, bounds[1]), (x, bounds[3]), lanes_y[i], g))

    intersections = []
    for j, y in enumerate(ys):
        for i, x in enumerate(xs):
            lights = bool(rng.random() < g.traffic_light_probability)
            intersections.append(Intersection(f"int_{i}_{j}", (x, y), (width_y[i], width_x[j]), lights))

    crosswalks, markings, medians = _crossings_and_markings(rng, roads, xs, ys, width_x, width_y, lanes_x, lanes_y, g, bounds)

    # Blocks: the cells between kerbs. Edge cells face a road on their inner sides only.
    x_edges = [bounds[0]] + [v for i, x in enumerate(xs) for v in (x - width_y[i] / 2, x + width_y[i] / 2)] + [bounds[2]]
    y_edges = [bounds[1]] + [v for j, y in enumerate(ys) for v in (y - width_x[j] / 2, y + width_x[j] / 2)] + [bounds[3]]
    sidewalks: list[Sidewalk] = list(medians)
    buildings: list[Building] = []
    furniture: list[Furniture] = []
    taken = Occupancy()
    if preset.furniture.median_hedges:
        furniture.extend(_median_hedges(rng, medians, preset, taken))
    for bj in range(n_xroads + 1):
        for bi in range(n_yroads + 1):
            block = _Rect(x_edges[2 * bi], y_edges[2 * bj], x_edges[2 * bi + 1], y_edges[2 * bj + 1])
            sw = {
                "w": sw_y[bi - 1] if bi > 0 else 0.0,
                "e": sw_y[bi] if bi < n_yroads else 0.0,
                "s": sw_x[bj - 1] if bj > 0 else 0.0,
                "n": sw_x[bj] if bj < n_xroads else 0.0,
            }
            tag = f"b{bi}_{bj}"
            strips = _block_sidewalks(tag, block, sw, g.curb_height)
            verges = {s.sidewalk_id: _verge_width(rng, g, s) for s in strips}
            for strip in strips:
                sidewalks.extend(_split_verge(strip, block, verges[strip.sidewalk_id]))
            lot = _Rect(block.x0 + sw["w"], block.y0 + sw["s"], block.x1 - sw["e"], block.y1 - sw["n"])
            if lot.w > 0.5 and lot.h > 0.5:
                sidewalks.append(Sidewalk(f"{tag}_lot", preset.buildings.lot_surface, ((lot.x0 + lot.x1) / 2, (lot.y0 + lot.y1) / 2),
                                          lot.w, lot.h, 0.0, g.curb_height))
                faces = {k: v > 0 for k, v in sw.items()}
                new_buildings = _block_buildings(rng, tag, lot, faces, preset)
                buildings.extend(new_buildings)
                if preset.furniture.hedge_probability > 0 and preset.buildings.lot_surface == "lawn":  # front gardens
                    furniture.extend(_lot_hedges(rng, tag, lot, faces, new_buildings, preset, taken))
            for strip in strips:
                furniture.extend(_strip_furniture(rng, strip, block, preset, taken, verges[strip.sidewalk_id]))
    for inter in intersections:
        furniture.extend(_corner_furniture(rng, inter, crosswalks, g, preset, taken))

    city = City(
        preset=preset.name,
        seed=int(seed),
        bounds=bounds,
        curb_height=g.curb_height,
        roads=tuple(roads),
        intersections=tuple(intersections),
        crosswalks=tuple(crosswalks),
        markings=tuple(markings),
        sidewalks=tuple(sidewalks),
        buildings=tuple(buildings),
        furniture=tuple(furniture),
        road_material=Material(jitter(rng, (0.045, 0.045, 0.05), 0.15), roughness=0.85),
        sidewalk_material=Material(jitter(rng, (0.30, 0.29, 0.27), 0.1), roughness=0.8),
        lawn_material=Material(jitter(rng, (0.05, 0.12, 0.03), 0.15), roughness=0.95),
    )
    return canonical(city)


# ---------------------------------------------------------------------------------------------
# Roads, lanes, crossings, markings
# ---------------------------------------------------------------------------------------------


def _make_road(road_id: str, axis: str, start, end, lanes: int, g) -> Road:
    """Lanes of a road: n each way, driving on the right; outside them a bike lane (if the preset
    has them), then a parking lane at the kerb."""
    heading = math.atan2(end[1] - start[1], end[0] - start[0])
    out = []
    for direction, (a, b) in (("fwd", (start, end)), ("bwd", (end, start))):
        # Right of the travel direction is -left; "fwd" lanes lie to the right of the centreline.
        side = -1.0 if direction == "fwd" else 1.0
        for i in range(lanes):
            off = side * (g.median_width / 2.0 + (i + 0.5) * g.lane_width)
            out.append(Lane(f"{road_id}/{direction}{i}", "driving", to_world(a, heading, 0, off), to_world(b, heading, 0, off), g.lane_width))
        outer = g.median_width / 2.0 + lanes * g.lane_width
        if g.bike_lane_width > 0:
            off = side * (outer + g.bike_lane_width / 2.0)
            out.append(Lane(f"{road_id}/bike_{direction}", "bike", to_world(a, heading, 0, off), to_world(b, heading, 0, off),
                            g.bike_lane_width))
            outer += g.bike_lane_width
        if g.parking_lanes:
            off = side * (outer + g.parking_width / 2.0)
            out.append(Lane(f"{road_id}/park_{direction}", "parking", to_world(a, heading, 0, off), to_world(b, heading, 0, off), g.parking_width))
    return Road(road_id, axis, start, end, _road_width(lanes, g), tuple(out))


def _crossings_and_markings(rng, roads, xs, ys, width_x, width_y, lanes_x, lanes_y, g, bounds):
    """Crosswalks and stop lines at each intersection approach; lane markings in between."""
    crosswalks: list[Crosswalk] = []
    markings: list[Marking] = []
    medians: list[Sidewalk] = []
    # blocked[road_id] = intervals along the road's axis (intersection boxes, crossings).
    for road in roads:
        along_axis = 0 if road.axis == "x" else 1
        heading = 0.0 if road.axis == "x" else math.pi / 2
        center_across = road.start[1 - along_axis]
        lanes = lanes_x[int(road.road_id[6:])] if road.axis == "x" else lanes_y[int(road.road_id[6:])]
        crossings = [(xs[i], width_y[i]) for i in range(len(xs))] if road.axis == "x" else [(ys[j], width_x[j]) for j in range(len(ys))]
        blocked = []
        for c, cross_w in crossings:
            for sign in (-1.0, 1.0):  # the approach on the low side (-1) and the high side (+1)
                edge = c + sign * cross_w / 2.0
                reach = 1.0
                if rng.random() < g.crosswalk_probability:
                    cw_w = float(rng.uniform(3.0, 4.5))
                    along = edge + sign * (0.5 + cw_w / 2.0)
                    center = (along, center_across) if road.axis == "x" else (center_across, along)
                    crosswalks.append(Crosswalk(f"cw_{road.road_id}_{len(crosswalks)}", center, road.width, cw_w,
                                                heading + math.pi / 2, 0.5, 0.5))
                    reach = 0.5 + cw_w + 1.0
                # Stop line across the lanes that approach from this side: from the low side
                # traffic travels +axis ("fwd" lanes, right of the centreline, across < 0).
                stop_along = edge + sign * (reach + 0.2)
                across = lanes * g.lane_width + g.bike_lane_width  # the bike lane stops at the line too
                center = _road_point(road.axis, center_across, stop_along, sign * (g.median_width / 2.0 + across / 2.0))
                markings.append(Marking("stop_line", center, 0.4, across, heading, "white"))
                blocked.append(tuple(sorted((edge, edge + sign * (reach + 0.4)))))
            blocked.append((c - cross_w / 2.0, c + cross_w / 2.0))
        lo, hi = (bounds[0], bounds[2]) if road.axis == "x" else (bounds[1], bounds[3])
        for a, b in _free_intervals(lo, hi, blocked):
            markings.extend(_segment_markings(road, heading, center_across, a, b, lanes, g, rng, (lo, hi)))
            if g.median_width > 0 and b - a > 4.0:  # the median stops short of stop lines and crosswalks
                center = _road_point(road.axis, center_across, (a + b) / 2.0, 0.0)
                medians.append(Sidewalk(f"{road.road_id}_median{len(medians)}", "lawn", center, b - a - 1.0, g.median_width,
                                        heading, g.curb_height, heading))
    return crosswalks, markings, medians


def _free_intervals(lo: float, hi: float, blocked: list) -> list[tuple[float, float]]:
    out, cursor = [], lo
    for a, b in sorted(blocked):
        if a > cursor + 1e-6:
            out.append((cursor, min(a, hi)))
        cursor = max(cursor, b)
    if cursor < hi - 1e-6:
        out.append((cursor, hi))
    return [(a, b) for a, b in out if b - a > 1.0]


def _road_point(axis: str, center_across: float, along: float, across: float) -> tuple[float, float]:
    """World point `along` a road's axis and `across` to the left of its +axis direction."""
    if axis == "x":
        return (along, center_across + across)
    return (center_across - across, along)  # left of +y is -x


def _segment_markings(road, heading, center_across, a, b, lanes, g, rng, bounds=None) -> list[Marking]:
    """Double centre line, dashed lane dividers, solid edge lines at the parking lanes; with
    `turn_lanes`, the inner lane of each junction approach is a left-turn lane: a solid divider
    over the last `turn_lane_length` metres and arrows (left in the turn lane, ahead elsewhere)."""
    def at(along: float, across: float):
        return _road_point(road.axis, center_across, along, across)

    out = []
    mid, length = (a + b) / 2.0, b - a
    lo, hi = bounds if bounds is not None else (a, b)
    if g.median_width > 0:  # a raised median: a white line along each of its kerbs
        for off in (-g.median_width / 2.0 - 0.2, g.median_width / 2.0 + 0.2):
            out.append(Marking("edge_line", at(mid, off), length, 0.12, heading, "white"))
    else:
        for off in (-0.1, 0.1):
            out.append(Marking("center_line", at(mid, off), length, 0.1, heading, "yellow"))
    dash, gap = 3.0, 6.0
    phase = float(rng.uniform(0, dash + gap))
    for side in (-1.0, 1.0):
        # side -1: lanes travelling +axis, meeting a junction at b; side +1: travelling -axis, at a.
        at_junction = b < hi - 1e-6 if side < 0 else a > lo + 1e-6
        turn = min(g.turn_lane_length, 0.45 * length) if g.turn_lanes and lanes >= 2 and at_junction else 0.0
        for i in range(1, lanes):
            off = side * (g.median_width / 2.0 + i * g.lane_width)
            da, db = a, b
            if i == 1 and turn > 0:
                da, db = (a, b - turn) if side < 0 else (a + turn, b)
                solid = (b - turn / 2.0) if side < 0 else (a + turn / 2.0)
                out.append(Marking("turn_divider", at(solid, off), turn, 0.15, heading, "white"))
            t = a + phase
            while t + dash < b:
                if t >= da and t + dash <= db:
                    out.append(Marking("lane_divider", at(t + dash / 2.0, off), dash, 0.12, heading, "white"))
                t += dash + gap
        if turn > 0:
            end = b if side < 0 else a
            travel = heading if side < 0 else heading + math.pi
            for i in range(lanes):
                base = at(end + side * (7.0 + 3.0), side * (g.median_width / 2.0 + (i + 0.5) * g.lane_width))
                out.extend(_arrow(base, travel, left=(i == 0)))
        outer = g.median_width / 2.0 + lanes * g.lane_width
        if g.bike_lane_width > 0:  # a solid line between the traffic and the bike lane
            out.append(Marking("edge_line", at(mid, side * outer), length, 0.15, heading, "white"))
            outer += g.bike_lane_width
        if g.parking_lanes:
            out.append(Marking("edge_line", at(mid, side * outer), length, 0.12, heading, "white"))
    return out


def _arrow(base: tuple[float, float], yaw: float, left: bool) -> list[Marking]:
    """A painted lane arrow from `base` along `yaw` (3 m ahead, or 2 m then a 1.2 m turn to the
    left), as flat strokes 0.15 m wide."""
    u = np.array([math.cos(yaw), math.sin(yaw)])
    p0 = np.asarray(base, dtype=np.float64)

    def stroke(a: np.ndarray, b: np.ndarray) -> Marking:
        c, d = (a + b) / 2.0, b - a
        return Marking("arrow", (float(c[0]), float(c[1])), float(np.hypot(*d)) + 0.15, 0.15, math.atan2(d[1], d[0]), "white")

    if left:
        bend = p0 + 2.0 * u
        lft = np.array([-u[1], u[0]])
        tip, point = bend + 1.2 * lft, yaw + math.pi / 2
        strokes = [stroke(p0, bend), stroke(bend, tip)]
    else:
        tip, point = p0 + 3.0 * u, yaw
        strokes = [stroke(p0, tip)]
    for turn in (math.radians(150), -math.radians(150)):
        back = np.array([math.cos(point + turn), math.sin(point + turn)])
        strokes.append(stroke(tip, tip + 0.9 * back))
    return strokes


# ---------------------------------------------------------------------------------------------
# Blocks: sidewalks and buildings
# ---------------------------------------------------------------------------------------------


def _block_sidewalks(tag: str, r: _Rect, sw: dict, curb: float) -> list[Sidewalk]:
    """Sidewalk strips along the block sides that face roads; west/east strips own the corners."""
    out = []
    ymid, xmid = (r.y0 + r.y1) / 2.0, (r.x0 + r.x1) / 2.0
    if sw["w"] > 0:
        out.append(Sidewalk(f"{tag}_sw_w", "sidewalk", (r.x0 + sw["w"] / 2, ymid), r.h, sw["w"], math.pi / 2, curb, math.pi / 2))
    if sw["e"] > 0:
        out.append(Sidewalk(f"{tag}_sw_e", "sidewalk", (r.x1 - sw["e"] / 2, ymid), r.h, sw["e"], math.pi / 2, curb, math.pi / 2))
    x0, x1 = r.x0 + sw["w"], r.x1 - sw["e"]
    if x1 - x0 > 0.1:
        if sw["s"] > 0:
            out.append(Sidewalk(f"{tag}_sw_s", "sidewalk", ((x0 + x1) / 2, r.y0 + sw["s"] / 2), x1 - x0, sw["s"], 0.0, curb, 0.0))
        if sw["n"] > 0:
            out.append(Sidewalk(f"{tag}_sw_n", "sidewalk", ((x0 + x1) / 2, r.y1 - sw["n"] / 2), x1 - x0, sw["n"], 0.0, curb, 0.0))
    del xmid
    return out


def _split_lots(rng: np.random.Generator, lot: _Rect, lot_width) -> list[_Rect]:
    """Guillotine cuts across the longer side until every lot is shorter than a drawn width."""
    stack, out = [lot], []
    while stack:
        r = stack.pop()
        limit = float(rng.uniform(*lot_width))
        if max(r.w, r.h) <= limit:
            out.append(r)
            continue
        f = float(rng.uniform(0.38, 0.62))
        if r.w >= r.h:
            x = r.x0 + f * r.w
            stack += [_Rect(r.x0, r.y0, x, r.y1), _Rect(x, r.y0, r.x1, r.y1)]
        else:
            y = r.y0 + f * r.h
            stack += [_Rect(r.x0, r.y0, r.x1, y), _Rect(r.x0, y, r.x1, r.y1)]
    return out


def _block_buildings(rng: np.random.Generator, tag: str, lot_area: _Rect, faces: dict, preset: Preset) -> list[Building]:
    b = preset.buildings
    curb = preset.grid.curb_height
    out = []
    for k, lot in enumerate(_split_lots(rng, lot_area, b.lot_width)):
        if rng.random() < b.empty_lot_probability:
            continue
        # Street sides get the setback, the others half the gap to the neighbour.
        street = {
            "w": faces["w"] and abs(lot.x0 - lot_area.x0) < 1e-6,
            "e": faces["e"] and abs(lot.x1 - lot_area.x1) < 1e-6,
            "s": faces["s"] and abs(lot.y0 - lot_area.y0) < 1e-6,
            "n": faces["n"] and abs(lot.y1 - lot_area.y1) < 1e-6,
        }
        inset = {s: float(rng.uniform(*b.setback)) if street[s] else float(rng.uniform(*b.side_gap)) / 2.0 for s in "wesn"}
        r = _Rect(lot.x0 + inset["w"], lot.y0 + inset["s"], lot.x1 - inset["e"], lot.y1 - inset["n"])
        if min(r.w, r.h) < b.min_footprint:
            continue
        kind = pick(rng, b.footprints)
        floor_h = float(rng.uniform(*b.floor_height))
        floors = max(1, int(round(float(rng.uniform(*b.height)) / floor_h)))
        top = curb + floors * floor_h
        rect = ((r.x0, r.y0), (r.x1, r.y0), (r.x1, r.y1), (r.x0, r.y1))
        if kind == "l_shape" and min(r.w, r.h) >= 2 * b.min_footprint:
            fx, fy = float(rng.uniform(0.35, 0.6)), float(rng.uniform(0.35, 0.6))
            corner = int(rng.integers(4))
            cut = _corner_cut(r, fx, fy, corner)
            parts = (BuildingPart(polygon_tuple(box(r.x0, r.y0, r.x1, r.y1).difference(cut)), curb, top),)
        elif kind == "tower" and floors > 5:
            podium = int(rng.integers(2, 5))
            f = float(rng.uniform(0.15, 0.3))
            t = _Rect(r.x0 + f * r.w, r.y0 + f * r.h, r.x1 - f * r.w, r.y1 - f * r.h)
            mid = curb + podium * floor_h
            parts = (
                BuildingPart(rect, curb, mid),
                BuildingPart(((t.x0, t.y0), (t.x1, t.y0), (t.x1, t.y1), (t.x0, t.y1)), mid, top),
            )
        else:
            gable = floors <= 3 and rng.random() < b.gable_probability
            roof_h = float(rng.uniform(0.25, 0.45)) * min(r.w, r.h) if gable else 0.0
            parts = (BuildingPart(rect, curb, top, "gable" if gable else "flat", roof_h),)
        house = b.gable_probability > 0 and floors <= 3
        wall = Material(jitter(rng, HOUSE_COLORS[int(rng.integers(len(HOUSE_COLORS)))] if house else WALL_COLORS[int(rng.integers(len(WALL_COLORS)))]),
                        roughness=float(rng.uniform(0.6, 0.95)))
        glass = Material(jitter(rng, (0.04, 0.055, 0.07), 0.2), roughness=float(rng.uniform(0.03, 0.12)), metallic=0.2)
        frame = Material(jitter(rng, (0.05, 0.05, 0.05) if rng.random() < 0.5 else (0.5, 0.5, 0.48)), roughness=0.5, metallic=0.5)
        facade = Facade(
            floor_height=floor_h,
            window_width=float(rng.uniform(0.9, 1.6)),
            window_height=float(rng.uniform(1.2, 0.7 * floor_h)),
            window_spacing=float(rng.uniform(*b.window_spacing)),
            wall=wall,
            window=glass,
            frame=frame,
            lit_fraction=float(rng.uniform(*b.lit_fraction)),
            seed=int(rng.integers(2**31)),
        )
        roof = Material(jitter(rng, ROOF_COLORS[int(rng.integers(len(ROOF_COLORS)))]), roughness=0.9)
        out.append(Building(f"building_{tag}_{k}", parts, facade, roof))
    return out


def _corner_cut(r: _Rect, fx: float, fy: float, corner: int) -> Polygon:
    cw, ch = fx * r.w, fy * r.h
    x0 = r.x0 if corner in (0, 3) else r.x1 - cw
    y0 = r.y0 if corner in (0, 1) else r.y1 - ch
    return box(x0, y0, x0 + cw, y0 + ch)


# ---------------------------------------------------------------------------------------------
# Street furniture
# ---------------------------------------------------------------------------------------------


def _footprint_square(center, size: float) -> tuple:
    return polygon_tuple(rect_polygon(center, size, size, 0.0))


def _furniture(fid: str, kind: str, pole_xy, pole_local: tuple[float, float], dims, yaw: float, base_z: float, params: dict,
               footprint) -> Furniture:
    """Furniture whose mesh origin (a pole's base) sits at `pole_local` in the cuboid's frame."""
    c, s = math.cos(yaw), math.sin(yaw)
    cx = pole_xy[0] - (pole_local[0] * c - pole_local[1] * s)
    cy = pole_xy[1] - (pole_local[0] * s + pole_local[1] * c)
    return Furniture(fid, kind, (cx, cy, base_z + dims[2] / 2.0), tuple(float(d) for d in dims), yaw, params, footprint)


def _add_if_free(item: Furniture, out: list[Furniture], taken: Occupancy, margin: float = 0.4) -> None:
    """Append `item` unless its footprint comes within `margin` of furniture already placed."""
    poly = Polygon(item.footprint)
    if not taken.collides(poly, margin):
        taken.add(poly)
        out.append(item)


def _kerb_sign(strip: Sidewalk, block: _Rect) -> float:
    """+1 when the strip's kerb (the side nearer the road, away from the block centre) is on the
    strip's left (+across), -1 when on its right."""
    to_center = np.array([(block.x0 + block.x1) / 2 - strip.center[0], (block.y0 + block.y1) / 2 - strip.center[1]])
    left = np.array([-math.sin(strip.yaw), math.cos(strip.yaw)])
    return -1.0 if float(left @ to_center) > 0 else 1.0


SIGNS = (("round", "red"), ("round", "blue"), ("triangle", "red"), ("square", "blue"), ("rect", "blue"))
CORNER_POLE = (5.8, 1.0)  # metres from the junction box's corner along one road and in from its kerb
VERGE_END = 6.5  # metres of paving kept at each end of a verged strip: crosswalk landings, corner poles
MIN_FOOTWAY = 1.8  # a verge never narrows the footway below this


def _verge_width(rng: np.random.Generator, g, strip: Sidewalk) -> float:
    """The grass verge of one strip (0: none); no draw at all when the preset has no verges, so
    presets without them keep their cities."""
    if g.verge_width[1] <= 0:
        return 0.0
    v = min(float(rng.uniform(*g.verge_width)), strip.width - MIN_FOOTWAY)
    return v if v >= 0.6 and strip.length - 2 * VERGE_END > 3.0 else 0.0


def _split_verge(strip: Sidewalk, block: _Rect, verge: float) -> list[Sidewalk]:
    """A road-side strip as footway (building side, full length), and, when it has a verge, a
    grass verge along the kerb with paved ends (where crosswalks land and corners are walked)."""
    if verge <= 0:
        return [strip]
    k = _kerb_sign(strip, block)
    half_w = strip.width / 2.0

    def piece(sid: str, kind: str, along: float, across: float, length: float, width: float) -> Sidewalk:
        c = to_world(strip.center, strip.yaw, along, across)
        return Sidewalk(sid, kind, c, length, width, strip.yaw, strip.height, strip.road_yaw)

    kerb_mid = k * (half_w - verge / 2.0)
    end_along = strip.length / 2.0 - VERGE_END / 2.0
    return [
        piece(strip.sidewalk_id, "sidewalk", 0.0, -k * verge / 2.0, strip.length, strip.width - verge),
        piece(f"{strip.sidewalk_id}_verge", "lawn", 0.0, kerb_mid, strip.length - 2 * VERGE_END, verge),
        piece(f"{strip.sidewalk_id}_end0", "sidewalk", -end_along, kerb_mid, VERGE_END, verge),
        piece(f"{strip.sidewalk_id}_end1", "sidewalk", end_along, kerb_mid, VERGE_END, verge),
    ]


def _strip_furniture(rng: np.random.Generator, strip: Sidewalk, block: _Rect, preset: Preset, taken: Occupancy,
                     verge: float = 0.0) -> list[Furniture]:
    """Street lights and trees on the kerb side (on the verge where there is one), bins and
    hydrants, planters, benches by the buildings."""
    f = preset.furniture
    out: list[Furniture] = []
    along_yaw = strip.yaw
    # Which side of the strip is the kerb: the side nearer the road, i.e. away from the block centre.
    left = np.array([-math.sin(along_yaw), math.cos(along_yaw)])
    kerb_sign = _kerb_sign(strip, block)  # +1: kerb on the strip's left
    road_yaw = math.atan2(kerb_sign * left[1], kerb_sign * left[0])  # facing the road
    z = strip.height
    margin = strip.width + 4.0  # keep clear of the corners (crosswalks, traffic lights)
    lo, hi = -strip.length / 2 + margin, strip.length / 2 - margin
    if hi <= lo:
        return out

    def at(along: float, from_kerb: float):
        across = kerb_sign * (strip.width / 2.0 - from_kerb)
        return to_world(strip.center, along_yaw, along, across)

    def add(item: Furniture) -> None:
        _add_if_free(item, out, taken)

    # On a verge, poles and trunks stand in its middle; the footway starts behind it.
    pole_at, tree_at, foot = (verge / 2.0, verge / 2.0, verge) if verge > 0 else (0.45, min(1.3, strip.width / 2), 0.0)
    n = len(taken.polygons)
    if f.street_light_spacing > 0:
        t = lo + float(rng.uniform(0, f.street_light_spacing / 2))
        while t <= hi:
            h, arm = float(rng.uniform(7.0, 9.0)), float(rng.uniform(1.2, 2.2))
            p = at(t, pole_at)
            dims = (arm + 0.35, 0.45, h)
            add(_furniture(f"{strip.sidewalk_id}_light{n + len(out)}", "street_light", p, (-dims[0] / 2 + 0.12, 0.0), dims, road_yaw, z,
                           {"arm": arm, "pole_radius": 0.09, "lamp": True, "clearance": h - 0.6}, _footprint_square(p, 0.4)))
            t += f.street_light_spacing
    if f.tree_spacing > 0:
        t = lo + float(rng.uniform(0, f.tree_spacing))
        while t <= hi:
            if rng.random() < f.tree_probability:
                species = pick(rng, f.tree_species) if len(f.tree_species) > 1 else next(iter(f.tree_species))
                trunk, dims = _tree_shape(rng, species, strip.width)
                p = at(t, tree_at)
                params = {"trunk_height": trunk, "trunk_radius": float(rng.uniform(0.1, 0.18)), "clearance": trunk,
                          "leaf_color": jitter(rng, (0.06, 0.16, 0.04), 0.25)}
                if species != "round":  # round is the builder's default; its params stay as they were
                    params["species"] = species
                add(_furniture(f"{strip.sidewalk_id}_tree{n + len(out)}", "tree", p, (0.0, 0.0), dims, float(rng.uniform(0, 2 * math.pi)), z,
                               params, _footprint_square(p, 0.8)))
            t += f.tree_spacing
    length = hi - lo
    for kind, rate in (("bin", f.bins_per_100m), ("hydrant", f.hydrants_per_100m), ("bench", f.benches_per_100m)):
        for _ in range(int(rng.poisson(rate * length / 100.0))):
            t = float(rng.uniform(lo, hi))
            if kind == "bench":
                p = at(t, strip.width - 0.45)
                dims, yaw = (1.8, 0.6, 0.85), road_yaw - math.pi / 2  # its seat faces +y: the road
                fp = polygon_tuple(rect_polygon(p, 1.8, 0.6, road_yaw + math.pi / 2))
                add(Furniture(f"{strip.sidewalk_id}_{kind}{n + len(out)}", kind, (p[0], p[1], z + dims[2] / 2), dims, yaw,
                              {"facing": road_yaw}, fp))
                continue
            if kind == "bin":
                p, dims, size = at(t, foot + 0.5), (0.55, 0.55, 0.95), 0.55
            else:
                p, dims, size = at(t, foot + 0.35), (0.35, 0.35, 0.75), 0.35
            add(Furniture(f"{strip.sidewalk_id}_{kind}{n + len(out)}", kind, (p[0], p[1], z + dims[2] / 2), dims, road_yaw, {},
                          _footprint_square(p, size)))

    def behind_footway(kind: str, name: str, per_100m: float, sizes, setback: float, yaw: float, params) -> None:
        """Poisson(per_100m) items of `kind` at uniform points along the strip, each a box along it
        whose l, w, h are drawn from the ranges `sizes`, standing `setback` m behind the footway's
        start; `params()` draws its params (after its size, as the draws have always run)."""
        for _ in range(int(rng.poisson(per_100m * length / 100.0))):
            t = float(rng.uniform(lo, hi))
            bl, bw, bh = (float(rng.uniform(*size)) for size in sizes)
            p = at(t, foot + setback + bw / 2)
            fp = polygon_tuple(rect_polygon(p, bl, bw, along_yaw))
            add(Furniture(f"{strip.sidewalk_id}_{name}{n + len(out)}", kind, (p[0], p[1], z + bh / 2), (bl, bw, bh), yaw,
                          params(), fp))

    if f.bus_shelters_per_100m > 0 and strip.width - foot >= 3.4:  # a shelter and a footway behind it
        # open side (+y) towards the road, like a bench
        behind_footway("bus_shelter", "shelter", f.bus_shelters_per_100m, ((3.5, 5.5), (1.3, 1.6), (2.4, 2.7)), 0.5,
                       road_yaw - math.pi / 2, lambda: {"ad_panel": bool(rng.random() < 0.7)})
    if f.planters_per_100m > 0 and strip.width - foot >= 2.6:  # leave a footway beside the planter
        behind_footway("planter", "planter", f.planters_per_100m, ((1.2, 2.2), (0.6, 0.9), (0.9, 1.5)), 0.3, along_yaw,
                       lambda: {"box_height": float(rng.uniform(0.4, 0.6)),
                                "leaf_color": jitter(rng, (0.06, 0.16, 0.04), 0.25),
                                "material": ("concrete", "wood", "metal")[int(rng.integers(3))]})
    return out


def _median_hedges(rng: np.random.Generator, medians: list[Sidewalk], preset: Preset, taken: Occupancy) -> list[Furniture]:
    """Clipped shrub rows along the middle of each median (a green belt, as on DAIR-V2X's
    junction roads), 0.5 m in from each kerb, in runs of 8-25 m with gaps."""
    out: list[Furniture] = []
    for m in medians:
        width = m.width - 1.0
        if width < 0.4:
            continue
        t = -m.length / 2.0 + float(rng.uniform(0.5, 2.0))
        while t < m.length / 2.0 - 2.0:
            length = min(float(rng.uniform(8.0, 25.0)), m.length / 2.0 - 0.5 - t)
            height = float(rng.uniform(0.6, 1.1))
            if length >= 2.0:
                c = to_world(m.center, m.yaw, t + length / 2.0, 0.0)
                poly = rect_polygon(c, length, width, m.yaw)
                item = Furniture(f"{m.sidewalk_id}_hedge{len(out)}", "hedge", (c[0], c[1], m.height + height / 2), (length, width, height),
                                 m.yaw, {"leaf_color": jitter(rng, (0.05, 0.14, 0.035), 0.2)}, polygon_tuple(poly))
                _add_if_free(item, out, taken)
            t += length + float(rng.uniform(1.0, 3.0))
    return out


TREE_RANGES = {"conical": ((0.8, 1.5), (1.8, 3.2), (6.0, 11.0)), "columnar": ((1.0, 2.0), (1.2, 2.2), (8.0, 14.0)),
               "spreading": ((2.6, 3.5), (5.0, 8.0), (8.0, 11.0))}
"""Per species but round: the ranges of its trunk height, crown diameter (the cuboid's l and w) and
overall height, in m, drawn in that order."""


def _tree_shape(rng: np.random.Generator, species: str, strip_width: float) -> tuple[float, tuple[float, float, float]]:
    """(trunk height, cuboid dims) of a street tree of `species`, in the ranges of the tree
    builder's contract (scenes/assets/props.py): round limes and maples, conical conifers,
    columnar poplars, spreading plane trees."""
    if species in TREE_RANGES:
        trunk_range, diameter_range, height_range = TREE_RANGES[species]
        trunk, d = float(rng.uniform(*trunk_range)), float(rng.uniform(*diameter_range))
        return trunk, (d, d, float(rng.uniform(*height_range)))
    trunk, crown = float(rng.uniform(2.3, 3.5)), float(rng.uniform(1.2, min(2.2, strip_width)))
    return trunk, (2 * crown, 2 * crown, trunk + 1.8 * crown)


def _lot_hedges(rng: np.random.Generator, tag: str, lot: _Rect, faces: dict, buildings: list[Building], preset: Preset,
                taken: Occupancy) -> list[Furniture]:
    """Hedges along the street sides of a block's lot ground (front gardens), in runs of 6 to 18 m
    with gaps for gates and drives; none where a building stands within 0.3 m."""
    f = preset.furniture
    out: list[Furniture] = []
    walls = Occupancy()
    for b in buildings:
        for part in b.parts:
            walls.add(Polygon(part.footprint))
    # (side, start, end, fixed coordinate inside the lot, axis along which the hedge runs)
    sides = (("s", lot.x0, lot.x1, lot.y0, 0), ("n", lot.x0, lot.x1, lot.y1, 0),
             ("w", lot.y0, lot.y1, lot.x0, 1), ("e", lot.y0, lot.y1, lot.x1, 1))
    for side, a, b, edge, axis in sides:
        if not faces[side]:
            continue
        inward = 1.0 if side in ("s", "w") else -1.0
        t = a + float(rng.uniform(0.5, 3.0))
        while t < b - 3.0:
            length = min(float(rng.uniform(6.0, 18.0)), b - 0.5 - t)
            width, height = float(rng.uniform(0.6, 1.0)), float(rng.uniform(0.8, 1.6))
            if length >= 3.0 and rng.random() < f.hedge_probability:
                off = edge + inward * (0.3 + width / 2.0)
                mid = t + length / 2.0
                c = (mid, off) if axis == 0 else (off, mid)
                yaw = 0.0 if axis == 0 else math.pi / 2
                poly = rect_polygon(c, length, width, yaw)
                if not walls.collides(poly, 0.3):
                    item = Furniture(f"{tag}_hedge{len(out)}", "hedge", (c[0], c[1], preset.grid.curb_height + height / 2),
                                     (length, width, height), yaw, {"leaf_color": jitter(rng, (0.05, 0.14, 0.035), 0.2)},
                                     polygon_tuple(poly))
                    _add_if_free(item, out, taken)
            t += length + float(rng.uniform(1.5, 4.0))
    return out


def _corner_furniture(rng, inter: Intersection, crosswalks, g, preset: Preset, taken: Occupancy) -> list[Furniture]:
    """Traffic lights at the near-right corner of each approach, bollards at the corners."""
    out: list[Furniture] = []
    cx, cy = inter.center
    wy, wx = inter.size  # wy: width of the road along y (extent in x); wx: of the road along x
    z = g.curb_height
    # Approach heading h; the corner to its right just before the box; arm over the road to the left.
    for k, (hx, hy) in enumerate(((1, 0), (-1, 0), (0, 1), (0, -1))):
        if not inter.traffic_lights:
            break
        road_half, cross_half = (wx / 2, wy / 2) if hx else (wy / 2, wx / 2)
        rx, ry = hy, -hx  # right of h
        px = cx - hx * (cross_half + 0.6) + rx * (road_half + 0.6)
        py = cy - hy * (cross_half + 0.6) + ry * (road_half + 0.6)
        arm = float(np.clip(road_half - 1.0, 2.0, 9.0))
        height = float(rng.uniform(5.8, 6.6))
        dims = (arm + 0.6, 0.5, height)
        yaw = math.atan2(-ry, -rx)  # the arm points left of h, over the road
        out.append(_furniture(f"{inter.intersection_id}_tl{k}", "traffic_light", (px, py), (-dims[0] / 2 + 0.12, 0.0), dims, yaw, z,
                              {"arm": arm, "pole_radius": 0.1, "clearance": height - 1.3, "faces": math.atan2(-hy, -hx)},
                              _footprint_square((px, py), 0.45)))
    if preset.furniture.signpost_probability > 0:
        # A sign at the right kerb of an approach, 7-10 m before the junction, facing its traffic.
        for k, (hx, hy) in enumerate(((1, 0), (-1, 0), (0, 1), (0, -1))):
            if rng.random() >= preset.furniture.signpost_probability:
                continue
            road_half, cross_half = (wx / 2, wy / 2) if hx else (wy / 2, wx / 2)
            back = float(rng.uniform(7.0, 10.0))
            px = cx - hx * (cross_half + back) + hy * (road_half + 0.5)
            py = cy - hy * (cross_half + back) - hx * (road_half + 0.5)
            shape, color = SIGNS[int(rng.integers(len(SIGNS)))]
            dims = (0.1, float(rng.uniform(0.55, 0.85)), float(rng.uniform(2.3, 3.0)))
            item = Furniture(f"{inter.intersection_id}_sign{k}", "signpost", (px, py, z + dims[2] / 2), dims,
                             math.atan2(-hy, -hx), {"shape": shape, "color": color}, _footprint_square((px, py), 0.2))
            _add_if_free(item, out, taken, 0.3)
    if preset.furniture.corner_poles:
        # A tall street light on each corner, its arm reaching over the junction: the poles
        # roadside cameras share at signalised junctions (DAIR-V2X's infrastructure views).
        for k, (sx, sy) in enumerate(((1, 1), (-1, 1), (-1, -1), (1, -1))):
            # By the kerb just past the crosswalk's landing, off the corner's diagonal, so a camera
            # on it looks across the junction past (not into) the corner's traffic light.
            a, b = CORNER_POLE if k % 2 == 0 else CORNER_POLE[::-1]
            px, py = cx + sx * (wy / 2 + a), cy + sy * (wx / 2 + b)
            h, arm = float(rng.uniform(8.0, 10.0)), float(rng.uniform(1.8, 2.8))
            dims = (arm + 0.35, 0.45, h)
            # The arm reaches over the road and away from the junction: out of the mounted camera's view.
            ax, ay = (0.5 * sx, -sy) if k % 2 == 0 else (-sx, 0.5 * sy)
            item = _furniture(f"{inter.intersection_id}_pole{k}", "street_light", (px, py), (-dims[0] / 2 + 0.12, 0.0), dims,
                              math.atan2(ay, ax), z, {"arm": arm, "pole_radius": 0.12, "lamp": True, "clearance": h - 0.6},
                              _footprint_square((px, py), 0.45))
            _add_if_free(item, out, taken, 0.2)
    for k, (sx, sy) in enumerate(((1, 1), (-1, 1), (-1, -1), (1, -1))):
        for b in range(preset.furniture.bollards_per_corner):
            d = 1.2 + 1.3 * b
            for axis in (0, 1):
                px = cx + sx * (wy / 2 + (0.35 if axis == 0 else d))
                py = cy + sy * (wx / 2 + (d if axis == 0 else 0.35))
                fp = _footprint_square((px, py), 0.22)
                item = Furniture(f"{inter.intersection_id}_bollard{k}_{b}_{axis}", "bollard", (px, py, z + 0.45), (0.22, 0.22, 0.9), 0.0, {}, fp)
                _add_if_free(item, out, taken, 0.2)
    del crosswalks
    return out
