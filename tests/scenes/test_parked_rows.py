"""Kerb parking (issue 26's frame rate): slots in a junction's or crosswalk's clearance are passed
over before a vehicle is drawn for them, and a kerb's row is tested in one vectorised query;
the rows still keep clear of crossings, of each other and of what stood before."""

from __future__ import annotations

import numpy as np
import pytest
import shapely

from omnigen.scenes import placement
from omnigen.scenes.generate import SceneGenerator
from omnigen.scenes.shapes import Occupancy, rect_polygon


@pytest.fixture(scope="module")
def downtown():
    gen = SceneGenerator("downtown", 0)
    return gen, [gen.frame(0, i) for i in range(2)]


def test_collides_many_agrees_with_collides():
    rng = np.random.default_rng(3)
    occ = Occupancy()
    for _ in range(60):
        occ.add(rect_polygon(rng.uniform(0, 50, 2), rng.uniform(0.5, 5), rng.uniform(0.5, 3), rng.uniform(-3, 3)))
    polys = [rect_polygon(rng.uniform(0, 50, 2), rng.uniform(0.5, 5), rng.uniform(0.5, 3), rng.uniform(-3, 3)) for _ in range(300)]
    for margin in (0.0, 0.1):
        many = occ.collides_many(np.array(polys, dtype=object), margin)
        one = [occ.collides(p, margin) for p in polys]
        assert many.tolist() == one
        assert 0 < many.sum() < len(polys)  # both answers occur
    assert not Occupancy().collides_many(np.array(polys, dtype=object)).any()


def _counting_trees(monkeypatch) -> list[int]:
    """The sizes of the STRtrees built from now on (shapes and placement look shapely.STRtree up
    at each call)."""
    built, real = [], shapely.STRtree
    monkeypatch.setattr(shapely, "STRtree", lambda geoms, *a, **k: built.append(len(geoms)) or real(geoms, *a, **k))
    return built


def test_a_frozen_occupancy_keeps_its_tree_and_still_finds_later_polygons(monkeypatch):
    """freeze() builds collides_many's tree once (a city's obstacles); copies share it; polygons
    added after it (a frame's work zones) are found through a small tree of their own."""
    rng = np.random.default_rng(5)
    box = lambda: rect_polygon(rng.uniform(0, 50, 2), rng.uniform(0.5, 5), rng.uniform(0.5, 3), rng.uniform(-3, 3))  # noqa: E731
    static = Occupancy()
    for _ in range(60):
        static.add(box())
    static.freeze()
    polys = np.array([box() for _ in range(300)], dtype=object)
    built = _counting_trees(monkeypatch)
    frame = static.copy()
    assert frame.collides_many(polys, 0.1).tolist() == [static.collides(p, 0.1) for p in polys]
    assert built == []  # nothing added since freeze: the kept tree alone
    for _ in range(5):
        frame.add(box())
    many = frame.collides_many(polys, 0.1)
    assert many.tolist() == [frame.collides(p, 0.1) for p in polys]
    assert built == [5]  # only the polygons added since freeze
    assert (many & ~static.collides_many(polys, 0.1)).any()  # the added ones count
    assert static.collides_many(polys, 0.1).tolist() == [static.collides(p, 0.1) for p in polys]  # the copy's adds stay out


def test_free_many_builds_no_tree_for_a_citys_static_obstacles(downtown, monkeypatch):
    """A frame's world queries the trees its city's _Static keeps (obstacles and canopies) and
    gives the same answers as `free`, one polygon at a time."""
    gen, _ = downtown
    world = placement._world(gen.city)
    assert world.overhead_tree is not None and world.ground._tree is not None
    rng = np.random.default_rng(1)
    x0, y0, x1, y1 = shapely.total_bounds([c for c, _ in world.overhead])
    polys = np.array([rect_polygon((rng.uniform(x0, x1), rng.uniform(y0, y1)), 4.5, 1.8, rng.uniform(-3, 3))
                      for _ in range(2000)], dtype=object)
    tops = rng.uniform(1.0, 12.0, len(polys))
    built = _counting_trees(monkeypatch)
    ok = world.free_many(polys, tops)
    assert built == []
    assert ok.tolist() == [world.free(p, t) for p, t in zip(polys, tops)]
    assert 0 < ok.sum() < len(polys)


def test_parked_vehicles_keep_clear_of_junctions_and_crosswalks(downtown):
    """6 m round intersection boxes and 1.5 m either side of crosswalks, 0.5 m nose and tail."""
    _, scenes = downtown
    city = scenes[0].city
    zones = [rect_polygon(i.center, i.size[0] + 12.0, i.size[1] + 12.0, 0.0) for i in city.intersections]
    zones += [rect_polygon(c.center, c.length, c.width + 3.0, c.yaw) for c in city.crosswalks]
    tree = shapely.STRtree(zones)
    n = 0
    for scene in scenes:
        for a in scene.agents:
            if a.state != "parked":
                continue
            n += 1
            body = rect_polygon(a.center[:2], a.dims[0] + 0.9, a.dims[1], a.yaw)
            assert len(tree.query(body, predicate="intersects")) == 0, a.name
    assert n > 300


def test_parked_rows_do_not_overlap_each_other_or_obstacles(downtown):
    _, scenes = downtown
    for scene in scenes:
        polys = [rect_polygon(a.center[:2], a.dims[0], a.dims[1], a.yaw) for a in scene.agents]
        tree = shapely.STRtree(polys)
        a, b = tree.query(polys, predicate="intersects")
        assert (a == b).all()  # each footprint meets only itself
        buildings = [shapely.Polygon(p.footprint) for bl in scene.city.buildings for p in bl.parts]
        assert len(shapely.STRtree(buildings).query(polys, predicate="intersects")[0]) == 0


def test_parking_spans_are_where_the_lane_meets_a_crossing_zone(downtown):
    gen, _ = downtown
    p = placement._Placer(gen.city, np.random.default_rng(0))
    zones = p.static.crossing_zones
    checked = 0
    for lane in p.parking:
        spans = p.parking_spans(lane)
        assert spans == sorted(spans) and all(a <= b for a, b in spans)
        assert all(b0 < a1 for (_, b0), (a1, _) in zip(spans, spans[1:]))  # merged: disjoint
        for t in np.arange(0.25, lane.length, 0.5):  # a thin slice of the lane across it
            mid = placement.to_world(lane.start, lane.heading, float(t), 0.0)
            inside = zones.collides(rect_polygon(mid, 0.05, lane.width, lane.heading))
            assert inside == (placement._meets(spans, t - 0.025, t + 0.025) is not None), (lane.lane_id, t)
            checked += inside
    assert checked > 0


def test_slots_in_a_clearance_draw_no_vehicle(downtown, monkeypatch):
    """Before, every slot drew its vehicle first and half of downtown's draws were then dropped in
    a clearance; now a draw is wasted only where a long vehicle reaches the next clearance or a
    lane's end."""
    gen, _ = downtown
    draws = []
    real = placement._Placer.asset
    monkeypatch.setattr(placement._Placer, "asset", lambda self, *a, **k: draws.append(1) or real(self, *a, **k))
    p = placement._Placer(gen.city, np.random.default_rng([0, 7]))
    p.parked(0.9, gen.preset.agents.parked_mix)
    placed = sum(a.state == "parked" for a in p.agents)
    assert placed > 100
    assert len(draws) <= 1.1 * placed + len(p.parking)
