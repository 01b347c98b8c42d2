"""scenes/: the pure-Python description (no bpy, no GL): determinism, presets, placement, weather."""

from __future__ import annotations

import hashlib
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from shapely.geometry import Polygon

from omnigen.scenes.description import Scene, from_json, to_json
from omnigen.scenes.generate import FrameOverrides, SceneGenerator, build_scene, randomize_frame
from omnigen.scenes.layout import build_city
from omnigen.scenes.preset import available_presets, load_preset, with_overrides
from omnigen.scenes.seeding import city_rng, frame_rng
from omnigen.scenes.shapes import rect_polygon
from omnigen.scenes.weather import draw_lighting, draw_weather, solar_position

ROOT = Path(__file__).resolve().parents[2]


# ---------------------------------------------------------------------------------------------
# Determinism
# ---------------------------------------------------------------------------------------------


def test_same_seed_same_bytes_and_json_round_trip():
    a, b = build_scene("tiny", 11), build_scene("tiny", 11)
    assert to_json(a) == to_json(b)
    assert from_json(Scene, to_json(a)) == a  # the live object is exactly what the JSON says
    assert to_json(build_scene("tiny", 12)) != to_json(a)


def test_sequence_fields_written_only_off_their_defaults():
    """A legacy frame's JSON has no instant, time or velocities (so its bytes are those from before
    sequences); a sequence instant's has them and reads back equal."""
    from dataclasses import replace

    a = build_scene("tiny", 11)
    text = to_json(a)
    assert '"instant"' not in text and '"velocities"' not in text and '"time"' not in text
    b = replace(a, instant=3, time=0.3, velocities=tuple((1.0, -0.5, 0.0) for _ in a.agents))
    assert '"instant":3' in to_json(b) and from_json(Scene, to_json(b)) == b


def test_same_bytes_in_a_fresh_interpreter():
    """Same (seed, preset) in another process (fresh hash seeds, fresh imports): same bytes."""
    code = (
        "import hashlib; from omnigen.scenes.generate import build_scene; from omnigen.scenes.description import to_json;"
        "print(hashlib.sha256(to_json(build_scene('tiny', 5)).encode()).hexdigest())"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True,
                         env={"PYTHONHASHSEED": "123", "PATH": ""}).stdout.strip()
    assert out == hashlib.sha256(to_json(build_scene("tiny", 5)).encode()).hexdigest()


def test_frames_are_independent_of_order_and_worker():
    gen = SceneGenerator("tiny", 4)
    f3 = to_json(gen.frame(9, 3))
    gen.frame(9, 1)
    assert to_json(gen.frame(9, 3)) == f3
    assert to_json(SceneGenerator("tiny", 4).frame(9, 3)) == f3  # another "worker"
    assert to_json(gen.frame(9, 4)) != f3
    assert gen.frame(9, 3).city is gen.city  # the static city is built once, not per frame


def test_fixing_the_weather_keeps_the_agents():
    gen = SceneGenerator("tiny", 4)
    free = gen.frame(2, 0)
    fixed = gen.frame(2, 0, FrameOverrides(weather="snow", time_of_day="night", fog_density=0.02))
    assert fixed.agents == free.agents
    assert fixed.weather.kind == "snow" and fixed.lighting.time_of_day == "night"
    assert fixed.weather.fog_density == pytest.approx(0.02)


def test_city_stream_is_not_frame_zero_stream():
    # numpy pads seeds with zeros: default_rng(s) == default_rng([s, 0]); the city must differ.
    assert city_rng(5).random() != frame_rng(5, 0).random()
    assert np.random.default_rng(5).random() == frame_rng(5, 0).random()


# ---------------------------------------------------------------------------------------------
# Presets
# ---------------------------------------------------------------------------------------------


def test_presets_load_by_name_and_path(tmp_path):
    names = available_presets()
    assert {"downtown", "arterial", "suburban"} <= set(names)
    for name in ("downtown", "arterial", "suburban"):
        p = load_preset(name)
        assert p.name == name and p.description
    path = tmp_path / "mine.toml"
    path.write_text((ROOT / "scenes/presets/tiny.toml").read_text().replace("blocks_x = 1", "blocks_x = 2"))
    assert load_preset(str(path)).grid.blocks_x == 2
    with pytest.raises(ValueError, match="unknown scene preset"):
        load_preset("atlantis")
    bad = tmp_path / "bad.toml"
    bad.write_text("[grid]\nblocks_xx = 3\n")
    with pytest.raises(ValueError, match="unknown fields"):
        load_preset(str(bad))
    with pytest.raises(ValueError, match="weather.kinds"):
        with_overrides(load_preset("tiny"), {"weather.kinds": {"hail": 1.0}})


def test_presets_differ_in_character():
    down, art, sub = (build_city(load_preset(n), 1) for n in ("downtown", "arterial", "suburban"))
    tallest = lambda c: max(p.top_z for b in c.buildings for p in b.parts)  # noqa: E731
    assert tallest(down) > 30 and tallest(sub) < 15
    lanes = lambda c: max(sum(1 for lane in r.lanes if lane.kind == "driving") for r in c.roads)  # noqa: E731
    assert lanes(art) == 6 and lanes(sub) == 2
    assert any(p.roof == "gable" for b in sub.buildings for p in b.parts)
    assert any(s.kind == "lawn" for s in sub.sidewalks)


# ---------------------------------------------------------------------------------------------
# Layout and placement
# ---------------------------------------------------------------------------------------------


def _scenes():
    for preset in ("tiny", "downtown", "arterial", "suburban"):
        gen = SceneGenerator(preset, 2)
        for frame in range(2 if preset == "tiny" else 1):
            yield gen.frame(2, frame)


SCENES = list(_scenes())


@pytest.mark.parametrize("scene", SCENES, ids=lambda s: f"{s.city.preset}-{s.frame_index}")
def test_no_two_cuboids_intersect_and_nothing_inside_buildings(scene, footprint):
    agents = scene.agents
    assert len(agents) > 10
    polys = [footprint(a) for a in agents]
    for i in range(len(agents)):
        for j in range(i + 1, len(agents)):
            za = (agents[i].center[2] - agents[i].dims[2] / 2, agents[i].center[2] + agents[i].dims[2] / 2)
            zb = (agents[j].center[2] - agents[j].dims[2] / 2, agents[j].center[2] + agents[j].dims[2] / 2)
            overlap_z = za[0] < zb[1] and zb[0] < za[1]
            assert not (overlap_z and polys[i].intersection(polys[j]).area > 1e-9), (agents[i].name, agents[j].name)
    buildings = [Polygon(p.footprint) for b in scene.city.buildings for p in b.parts]
    ground = [Polygon(f.footprint) for f in scene.city.furniture]
    for a, poly in zip(agents, polys):
        assert not any(poly.intersects(b) for b in buildings), a.name
        assert not any(poly.intersects(g) for g in ground), a.name
    assert [a.instance_id for a in agents] == list(range(1, len(agents) + 1))


@pytest.mark.parametrize("scene", SCENES[:3], ids=lambda s: f"{s.city.preset}-{s.frame_index}")
def test_agents_stand_where_they_belong(scene, footprint):
    city = scene.city
    lanes = {lane.lane_id: lane for r in city.roads for lane in r.lanes}
    def lane_poly(lane):
        mid = ((lane.start[0] + lane.end[0]) / 2, (lane.start[1] + lane.end[1]) / 2)
        return rect_polygon(mid, lane.length, lane.width + 0.02, lane.heading)

    driving = [(lane, lane_poly(lane)) for lane in lanes.values() if lane.kind == "driving"]
    parking = [(lane, lane_poly(lane)) for lane in lanes.values() if lane.kind == "parking"]
    walk = [rect_polygon(s.center, s.length + 0.02, s.width + 0.02, s.yaw) for s in city.sidewalks if s.kind == "sidewalk"]
    cross = [rect_polygon(c.center, c.length + 0.02, c.width + 0.02, c.yaw) for c in city.crosswalks]
    for a in scene.agents:
        poly = footprint(a)
        bottom = a.center[2] - a.dims[2] / 2
        if a.state == "moving":
            homes = [lane for lane, lp in driving if lp.contains(poly)]
            assert homes, a.name
            dyaw = min(abs(math.remainder(a.yaw - lane.heading, 2 * math.pi)) for lane in homes)
            assert dyaw <= math.radians(6.0) + 1e-6, a.name
            assert bottom == pytest.approx(0.0, abs=1e-6)
        elif a.state == "parked":
            assert any(lp.intersects(poly) and abs(math.remainder(a.yaw - lane.heading, 2 * math.pi)) < 0.06 for lane, lp in parking), a.name
        elif a.state in ("walking", "standing"):
            assert any(w.contains(poly) for w in walk), a.name
            assert bottom == pytest.approx(city.curb_height, abs=1e-6)
        elif a.state == "crossing":
            assert any(c.contains(poly) for c in cross), a.name
        if a.category in ("car", "van", "truck", "bus", "motorcyclist", "cyclist"):
            assert a.state in ("moving", "parked")


def test_every_class_appears_across_presets():
    seen = {a.category for s in SCENES for a in s.agents}
    assert {"car", "van", "truck", "bus", "pedestrian", "cyclist", "motorcyclist", "traffic_cone"} <= seen


def test_city_structure():
    city = build_city(load_preset("tiny"), 3)
    assert len(city.intersections) == 4 and len(city.crosswalks) == 16  # 4 approaches each, probability 1
    assert all(i.traffic_lights for i in city.intersections)
    kinds = {f.kind for f in city.furniture}
    assert {"street_light", "traffic_light", "bollard"} <= kinds
    assert {m.kind for m in city.markings} >= {"center_line", "stop_line", "edge_line", "lane_divider"}
    xmin, ymin, xmax, ymax = city.bounds
    for b in city.buildings:
        for p in b.parts:
            pts = np.asarray(p.footprint)
            assert xmin <= pts[:, 0].min() and pts[:, 0].max() <= xmax and ymin <= pts[:, 1].min() and pts[:, 1].max() <= ymax
            assert Polygon(p.footprint).is_valid and Polygon(p.footprint).exterior.is_ccw
    # Buildings never stand on roads or sidewalks.
    ways = [rect_polygon(s.center, s.length, s.width, s.yaw) for s in city.sidewalks if s.kind == "sidewalk"]
    for r in city.roads:
        ways.append(rect_polygon(((r.start[0] + r.end[0]) / 2, (r.start[1] + r.end[1]) / 2),
                                 math.dist(r.start, r.end), r.width, math.atan2(r.end[1] - r.start[1], r.end[0] - r.start[0])))
    for b in city.buildings:
        for p in b.parts:
            assert all(Polygon(p.footprint).intersection(w).area < 1e-6 for w in ways), b.building_id


# ---------------------------------------------------------------------------------------------
# Weather and lighting
# ---------------------------------------------------------------------------------------------


def test_sun_position():
    el, az = solar_position(45.0, 80, 12.0)  # near the March equinox, solar noon
    assert el == pytest.approx(45.0, abs=1.5) and az == pytest.approx(180.0, abs=0.5)
    el, az = solar_position(45.0, 172, 8.0)  # June morning: sun in the east, up
    assert 20 < el < 45 and 60 < az < 110
    assert solar_position(45.0, 172, 0.0)[0] < -15


@pytest.mark.parametrize("time_of_day", ["dawn", "morning", "noon", "afternoon", "dusk", "night"])
def test_time_of_day_matches_sun_and_lights(time_of_day):
    rng = np.random.default_rng(0)
    for _ in range(20):
        w = draw_weather(rng, {"clear": 1.0})
        light = draw_lighting(rng, {"noon": 1.0}, 45.0, w, time_of_day)
        el = light.sun_elevation
        if time_of_day in ("dawn", "dusk"):
            assert -4.5 <= el <= 8.5
            assert (light.sun_azimuth < 180) == (time_of_day == "dawn")
        elif time_of_day == "night":
            assert el < -11.5 and light.street_lights_on and light.vehicle_lights_on and light.windows_lit
            assert light.sun_strength == 0
        else:
            assert el > 7.5 and not light.street_lights_on and light.sun_strength > 0


def test_weather_kinds():
    rng = np.random.default_rng(1)
    fog = draw_weather(rng, {"fog": 1.0})
    assert 320 < fog.visibility < 980 and fog.precipitation == 0
    rain = draw_weather(rng, {"rain": 1.0})
    assert rain.wetness >= 0.6 and rain.precipitation > 0 and rain.snow_cover == 0
    snow = draw_weather(rng, {"snow": 1.0})
    assert snow.snow_cover >= 0.3
    clear = draw_weather(rng, {"clear": 1.0})
    assert clear.visibility > 4000 and clear.wetness == 0
    assert draw_weather(rng, {"clear": 1.0}, fog_density=0.0).visibility == math.inf
    with pytest.raises(ValueError):
        draw_weather(rng, {"clear": 1.0}, kind="hail")


def test_weather_is_drawn_from_the_preset_distribution():
    gen = SceneGenerator(with_overrides(load_preset("tiny"), {"weather.kinds": {"rain": 1.0}}), 1)
    assert {gen.frame(1, i).weather.kind for i in range(4)} == {"rain"}
    scene = randomize_frame(gen.city, gen.preset, 1, 0, FrameOverrides(time_of_day="noon"))
    assert scene.lighting.time_of_day == "noon"
