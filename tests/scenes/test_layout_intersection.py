"""scenes/layout.py: the intersection preset (wide approaches, turn lanes, crosswalks on every arm,
corner poles the pole rig mounts on), grass verges, hedges; rigs/sampling.py on those corners."""

from __future__ import annotations

import math

import numpy as np
import pytest
from shapely.geometry import Polygon
from shapely.ops import unary_union

from omnigen.rigs.rig import load_rig
from omnigen.rigs.sampling import POLE_MOUNT, Obstacles, corner_pole, draw_camera, rig_rng
from omnigen.scenes.generate import SceneGenerator
from omnigen.scenes.layout import build_city
from omnigen.scenes.preset import load_preset, with_overrides
from omnigen.scenes.shapes import rect_polygon


def road_polygon(r) -> Polygon:
    return rect_polygon(((r.start[0] + r.end[0]) / 2, (r.start[1] + r.end[1]) / 2), math.dist(r.start, r.end), r.width,
                        math.atan2(r.end[1] - r.start[1], r.end[0] - r.start[0]))


@pytest.fixture(scope="module")
def city():
    return build_city(load_preset("intersection"), 4)


def test_intersection_junctions_are_wide_signalised_and_crossed_on_every_arm(city):
    assert len(city.intersections) == 4
    assert all(i.traffic_lights for i in city.intersections)
    assert len(city.crosswalks) == 4 * 4  # every approach of every junction
    for r in city.roads:
        assert sum(lane.kind == "driving" for lane in r.lanes) >= 6  # 3 or 4 lanes each way
    for i in city.intersections:
        assert min(i.size) >= 6 * 3.5
    lights = [f for f in city.furniture if f.kind == "traffic_light"]
    assert len(lights) == 16


def test_turn_lanes_have_solid_dividers_and_arrows_on_the_road(city):
    kinds = {m.kind for m in city.markings}
    assert {"turn_divider", "arrow", "stop_line"} <= kinds
    roads = [road_polygon(r) for r in city.roads]
    boxes = [rect_polygon(i.center, i.size[0], i.size[1], 0.0) for i in city.intersections]
    for m in city.markings:
        if m.kind in ("turn_divider", "arrow"):
            poly = rect_polygon(m.center, m.length, m.width, m.yaw)
            assert any(r.contains(poly) for r in roads), m
            assert not any(b.intersects(poly) for b in boxes), m  # before the junction, not in it
    # one solid divider per approach (4 junctions x 4 approaches, roads end at the city bounds)
    assert sum(m.kind == "turn_divider" for m in city.markings) == 16
    # no dashes overlap a solid divider
    solids = [rect_polygon(m.center, m.length, 0.3, m.yaw) for m in city.markings if m.kind == "turn_divider"]
    dashes = [rect_polygon(m.center, m.length, m.width, m.yaw) for m in city.markings if m.kind == "lane_divider"]
    assert not any(s.intersection(d).area > 1e-6 for s in solids for d in dashes)


def test_presets_without_turn_lanes_have_none():
    city = build_city(load_preset("downtown"), 4)
    assert not any(m.kind in ("turn_divider", "arrow") for m in city.markings)


def test_corner_poles_stand_on_the_footway_and_carry_the_pole_camera(city):
    walk = unary_union([rect_polygon(s.center, s.length + 0.01, s.width + 0.01, s.yaw)
                        for s in city.sidewalks if s.kind == "sidewalk"])
    roads = [road_polygon(r) for r in city.roads]
    for inter in city.intersections:
        for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1)):
            pole = corner_pole(city, inter, sx, sy)
            assert pole is not None and pole.kind == "street_light"
            foot = Polygon(pole.footprint)
            assert walk.contains(foot)  # paved (the verges stop short of the corners)
            assert not any(r.intersects(foot) for r in roads)
            axis = np.mean(np.asarray(pole.footprint), axis=0)
            # on the corner's quadrant
            assert np.sign(axis[0] - inter.center[0]) == sx and np.sign(axis[1] - inter.center[1]) == sy

    scene = SceneGenerator("intersection", 4).frame(4, 0)
    rig = load_rig("pole")
    obstacles = Obstacles(scene)
    mounted = 0
    for i in range(40):
        cam = draw_camera(rig, scene, rig_rng(4, i), 320, 240)
        if cam.anchor != "intersection":
            continue
        poles = [f for f in scene.city.furniture if f.furniture_id.split("_pole")[0].startswith("int_") and "_pole" in f.furniture_id]
        d = min(math.dist(cam.position[:2], np.mean(np.asarray(f.footprint), axis=0)) for f in poles)
        assert d == pytest.approx(POLE_MOUNT, abs=1e-6)  # on a pole, not anywhere near the corner
        # looking into the junction
        inter = min(scene.city.intersections, key=lambda j: math.dist(j.center, cam.position[:2]))
        to_center = math.atan2(inter.center[1] - cam.position[1], inter.center[0] - cam.position[0])
        assert abs(math.remainder(cam.yaw - to_center, 2 * math.pi)) <= math.radians(25) + 1e-6
        mounted += not obstacles.blocked(cam.position)
    assert mounted >= 10


def test_cities_without_corner_poles_keep_the_old_corner_anchor():
    scene = SceneGenerator("downtown", 1).frame(1, 0)
    assert not any("_pole" in f.furniture_id for f in scene.city.furniture)
    cam = next(c for i in range(40) if (c := draw_camera(load_rig("pole"), scene, rig_rng(1, i), 320, 240)).anchor == "intersection")
    inter = min(scene.city.intersections, key=lambda j: math.dist(j.center, cam.position[:2]))
    off = np.abs(np.asarray(cam.position[:2]) - inter.center) - np.asarray(inter.size) / 2
    assert ((off >= 1.0 - 1e-9) & (off <= 3.0 + 1e-9)).all()


def test_verges_lie_between_kerb_and_footway_and_carry_the_trees():
    city = build_city(load_preset("arterial"), 2)
    verges = [s for s in city.sidewalks if s.sidewalk_id.endswith("_verge")]
    assert verges and all(v.kind == "lawn" and v.height == city.curb_height for v in verges)
    roads = [road_polygon(r) for r in city.roads]
    by_id = {s.sidewalk_id: s for s in city.sidewalks}
    for v in verges:
        vp = rect_polygon(v.center, v.length, v.width, v.yaw)
        assert any(vp.distance(r) < 1e-5 for r in roads), v.sidewalk_id  # at the kerb
        foot = by_id[v.sidewalk_id[: -len("_verge")]]
        fp = rect_polygon(foot.center, foot.length, foot.width, foot.yaw)
        assert fp.distance(vp) < 1e-5 and fp.intersection(vp).area < 1e-4  # beside it (to the rounding), not under it
        assert not any(fp.intersection(r).area > 1e-4 for r in roads)
        assert foot.width >= 1.8 - 1e-9
    # every piece of the split strips is disjoint from every other
    pieces = [rect_polygon(s.center, s.length, s.width, s.yaw) for s in city.sidewalks if s.kind in ("sidewalk", "lawn")
              and not s.sidewalk_id.endswith("_lot")]
    for i in range(len(pieces)):
        for j in range(i + 1, len(pieces)):
            assert pieces[i].intersection(pieces[j]).area < 1e-4
    verge_polys = [rect_polygon(v.center, v.length + 0.01, v.width + 0.01, v.yaw) for v in verges]
    trees = [f for f in city.furniture if f.kind == "tree"]
    on_verge = [t for t in trees if any(vp.contains(Polygon(t.footprint)) for vp in verge_polys)]
    assert len(on_verge) >= 0.5 * len(trees)


def test_hedges_front_the_lots_and_never_touch_a_building():
    preset = with_overrides(load_preset("suburban"), {"furniture.hedge_probability": 1.0})
    city = build_city(preset, 3)
    hedges = [f for f in city.furniture if f.kind == "hedge"]
    assert len(hedges) >= 5
    walls = [Polygon(p.footprint) for b in city.buildings for p in b.parts]
    lots = [rect_polygon(s.center, s.length + 0.01, s.width + 0.01, s.yaw) for s in city.sidewalks if s.sidewalk_id.endswith("_lot")]
    for h in hedges:
        poly = Polygon(h.footprint)
        assert poly.area == pytest.approx(h.dims[0] * h.dims[1], rel=1e-5)
        assert not any(poly.distance(w) < 0.3 - 1e-6 for w in walls)
        assert any(lot.contains(poly) for lot in lots)
    # agents keep out of hedges (they are ground obstacles like trunks)
    scene = SceneGenerator(preset, 3).frame(3, 0)
    for a in scene.agents:
        fp = rect_polygon(a.center[:2], a.dims[0], a.dims[1], a.yaw)
        assert not any(fp.intersects(Polygon(h.footprint)) for h in hedges), a.name


def test_signposts_and_planters_stand_on_the_footway_facing_their_traffic():
    city = build_city(load_preset("downtown"), 6)
    walk = unary_union([rect_polygon(s.center, s.length + 0.01, s.width + 0.01, s.yaw)
                        for s in city.sidewalks if s.kind in ("sidewalk", "lawn") and not s.sidewalk_id.endswith("_lot")])
    signs = [f for f in city.furniture if f.kind == "signpost"]
    planters = [f for f in city.furniture if f.kind == "planter"]
    assert signs and planters
    for f in signs + planters:
        assert walk.contains(Polygon(f.footprint)), f.furniture_id
    by_id = {i.intersection_id: i for i in city.intersections}
    for f in signs:
        inter = by_id[f.furniture_id.rsplit("_sign", 1)[0]]
        # the face (+x) looks back along the approach: away from the junction it guards
        away = np.subtract(f.center[:2], inter.center)
        face = np.array([math.cos(f.yaw), math.sin(f.yaw)])
        assert float(face @ away) > 0.9 * float(np.abs(away).max())


def test_cameras_keep_clear_of_tree_crowns_but_not_from_under_them():
    scene = SceneGenerator("suburban", 1).frame(1, 0)
    obstacles = Obstacles(scene)
    tree = max((f for f in scene.city.furniture if f.kind == "tree"), key=lambda f: f.dims[0])
    x, y, zc = tree.center
    r, top, base = tree.dims[0] / 2, zc + tree.dims[2] / 2, zc - tree.dims[2] / 2 + tree.params["clearance"]
    beside = np.array([x + r + 1.0, y, (base + top) / 2])  # 1 m from the crown, at its height
    assert obstacles.blocked(beside)
    assert not obstacles.blocked(np.array([x + r + 1.0, y, base - 1.0]))  # under the crown's edge
    assert not obstacles.blocked(np.array([x + r + 1.0, y, top + 1.0]))  # above the tree
    assert obstacles.blocked(np.array([x + 0.3, y, 1.0]))  # in the trunk


def test_medians_split_the_directions_and_stop_short_of_junctions_and_crosswalks(city):
    medians = [s for s in city.sidewalks if "_median" in s.sidewalk_id]
    assert medians and all(m.kind == "lawn" and m.width == pytest.approx(3.0) for m in medians)
    polys = [rect_polygon(m.center, m.length, m.width, m.yaw) for m in medians]
    lanes = [lane for r in city.roads for lane in r.lanes if lane.kind == "driving"]
    lane_polys = [rect_polygon(((ln.start[0] + ln.end[0]) / 2, (ln.start[1] + ln.end[1]) / 2), ln.length, ln.width, ln.heading)
                  for ln in lanes]
    boxes = [rect_polygon(i.center, i.size[0], i.size[1], 0.0) for i in city.intersections]
    cross = [rect_polygon(c.center, c.length, c.width, c.yaw) for c in city.crosswalks]
    for m in polys:
        assert not any(m.intersection(lp).area > 1e-3 for lp in lane_polys)  # touching, to the rounding
        assert not any(m.intersects(b) for b in boxes + cross)
    # the inner lanes run along the median's kerbs, one direction on each side
    for r in city.roads:
        inner = [ln for ln in r.lanes if ln.lane_id.endswith(("/fwd0", "/bwd0"))]
        gap = math.dist(*(np.mean([ln.start, ln.end], axis=0) for ln in inner))
        assert gap == pytest.approx(3.0 + 3.5, abs=1e-6)
    hedges = [f for f in city.furniture if f.kind == "hedge"]
    assert hedges and all(any(m.contains(Polygon(h.footprint)) for m in polys) for h in hedges)
    assert not any(m.kind == "center_line" for m in city.markings)  # no painted centre line where a median runs


def test_a_camera_right_behind_a_taller_agent_is_redrawn():
    scene = SceneGenerator("intersection", 3).frame(3, 0)
    obstacles = Obstacles(scene)
    bus = max((a for a in scene.agents if a.category in ("bus", "truck", "van")), key=lambda a: a.dims[2])
    d = np.array([math.cos(bus.yaw), math.sin(bus.yaw)])
    behind = np.asarray(bus.center[:2]) - d * (bus.dims[0] / 2 + 1.5)
    cam = np.array([behind[0], behind[1], 1.6])
    assert not obstacles.blocked(cam)  # 1.5 m from its back: clear of the 0.5 m margin ...
    assert obstacles.wall_ahead(cam, bus.yaw)  # ... but its back fills the view
    assert not obstacles.wall_ahead(cam, bus.yaw + math.pi)  # looking the other way
    assert not obstacles.wall_ahead(np.array([behind[0], behind[1], bus.dims[2] + 1.0]), bus.yaw)  # above it
