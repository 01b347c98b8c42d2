"""The raster preview's look (issue 26 items 2 and 4): procedural surfaces that belong to the world,
sun shadows where the city blocks the sun, light that follows the weather and the hour, and haze
thin enough to see through. Geometry is covered by test_scene_raster.py and test_render.py."""

from __future__ import annotations

import math

import numpy as np
import pytest
from shapely.geometry import Point, Polygon

from omnigen.camera import Camera, intrinsics_from_fov, look_at
from omnigen.scenes.generate import FrameOverrides
from omnigen.scenes.materials import PATTERNS, ground_material, ground_surface
from omnigen.scenes.preset import available_presets, load_preset
from omnigen.scenes.shapes import rect_polygon
from omnigen.scenes.weather import _WEATHER_RANGES, direct_sun, draw_weather

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

raster = pytest.importorskip("omnigen.scenes.raster_backend", reason="pyrender/PyOpenGL not installed")

W = H = 160


@pytest.fixture(scope="module")
def noon(noon_raster):
    gen, scene, rs = noon_raster  # tests/scenes/conftest.py
    return gen, scene, rs, intrinsics_from_fov(math.radians(60), W, H)


def _world_points(depth, K, R, t, mask):
    """World positions of the pixels in `mask` (camera z `depth`)."""
    v, u = np.nonzero(mask)
    z = depth[v, u]
    cam = np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1)
    return (cam - t) @ R, v, u


def _luma(rgb):
    return rgb.astype(np.float64) @ (0.299, 0.587, 0.114)


def test_frames_are_deterministic(noon):
    _, _, rs, K = noon
    R, t = look_at((25.0, -30.0, 20.0), (0.0, 0.0, 0.0))
    a, b = rs.render(Camera(K, R, t, W, H)), rs.render(Camera(K, R, t, W, H))
    assert np.array_equal(a.rgb, b.rgb)


def test_surfaces_belong_to_the_world_not_the_camera(noon):
    """Ground points seen from two cameras (same distance and angle, opposite sides) keep their
    colour, while the texture makes neighbouring ground points differ."""
    _, scene, rs, K = noon
    road = scene.city.roads[0]
    target = np.array([(road.start[0] + road.end[0]) / 2.0, (road.start[1] + road.end[1]) / 2.0, 0.0])
    views = [look_at(target + [dx, dy, 18.0], target) for dx, dy in ((-14.0, -14.0), (14.0, 14.0))]
    frames = [rs.render(Camera(K, R, t, W, H), effects=False) for R, t in views]
    (R0, t0), (R1, t1) = views
    ground = (frames[0].instance == 0) & np.isfinite(frames[0].depth)
    X, v, u = _world_points(frames[0].depth, K, R0, t0, ground)
    keep = (np.abs(X[:, 2]) < 0.05) & (np.hypot(X[:, 0] - target[0], X[:, 1] - target[1]) < 6.0)
    X, v, u = X[keep], v[keep], u[keep]
    cam1 = X @ R1.T + t1
    u1 = np.rint(K[0, 0] * cam1[:, 0] / cam1[:, 2] + K[0, 2]).astype(int)
    v1 = np.rint(K[1, 1] * cam1[:, 1] / cam1[:, 2] + K[1, 2]).astype(int)
    inside = (u1 >= 0) & (u1 < W) & (v1 >= 0) & (v1 < H)
    u, v, u1, v1, X = u[inside], v[inside], u1[inside], v1[inside], X[inside]
    seen = np.abs(frames[1].depth[v1, u1] - cam1[inside][:, 2]) < 0.05  # not hidden from camera 1
    assert seen.sum() > 200
    a, b = _luma(frames[0].rgb[v[seen], u[seen]]), _luma(frames[1].rgb[v1[seen], u1[seen]])
    assert np.median(np.abs(a - b)) < 4.0  # the same point looks the same from both sides
    assert a.std() > 4.0  # and the ground is not flat: a texture (and shadows) vary across it


def test_sun_shadows_fall_where_the_city_blocks_the_sun(noon, monkeypatch):
    """Pixels the shadow pass darkens are ground points whose way to the sun a building or an
    agent (vehicles cast shadows too: this view holds traffic crossing a junction) blocks."""
    _, scene, rs, K = noon
    R, t = look_at((-5.0, -45.0, 60.0), (0.0, 0.0, 0.0))
    shaded = rs.render(Camera(K, R, t, W, H), effects=False)
    monkeypatch.setattr(raster, "MIN_SUN_SHARE", 2.0)  # no shadow pass
    plain = rs.render(Camera(K, R, t, W, H), effects=False)
    monkeypatch.undo()
    darker = _luma(shaded.rgb) < 0.6 * _luma(plain.rgb)
    assert (_luma(shaded.rgb) <= _luma(plain.rgb) + 1.0).all()  # shadows only take light away
    X, _, _ = _world_points(shaded.depth, K, R, t, darker & (shaded.instance == 0) & np.isfinite(shaded.depth))
    X = X[X[:, 2] < 0.3]  # on the ground
    assert len(X) > 50
    sun = np.asarray(scene.lighting.sun_direction)
    parts = [(Polygon(p.footprint), p.top_z) for b in scene.city.buildings for p in b.parts]
    parts += [(rect_polygon(a.center[:2], a.dims[0], a.dims[1], a.yaw), a.center[2] + a.dims[2] / 2) for a in scene.agents]
    blocked = 0
    for x in X[:: max(1, len(X) // 80)]:
        for s in np.arange(0.5, 150.0, 0.5):
            q = x + s * sun
            if q[2] > 80.0:
                break
            if any(q[2] < top and poly.contains(Point(q[0], q[1])) for poly, top in parts):
                blocked += 1
                break
    assert blocked >= 0.9 * len(X[:: max(1, len(X) // 80)])


def test_overcast_light_is_soft_and_night_is_dark_under_lamps(noon):
    gen, _, _, _ = noon
    overcast = gen.frame(8, 0, FrameOverrides(weather="overcast", time_of_day="noon"))
    light = raster.illumination(overcast)
    if overcast.weather.cloud_cover >= 0.87:
        assert max(light.radiance) == 0.0
    assert light.sun_share < raster.MIN_SUN_SHARE or overcast.weather.cloud_cover < 0.8  # no hard shadows
    night = gen.frame(8, 0, FrameOverrides(weather="clear", time_of_day="night"))
    dark = raster.illumination(night)
    assert max(dark.radiance) == 0.0 and dark.exposure == raster.MAX_EXPOSURE
    day = raster.illumination(gen.frame(8, 0, FrameOverrides(weather="clear", time_of_day="noon")))
    assert day.sun_share > 0.6 and day.exposure < dark.exposure
    dusk = raster.illumination(gen.frame(8, 0, FrameOverrides(weather="clear", time_of_day="dusk")))
    if max(dusk.radiance) > 0:
        assert dusk.radiance[2] < 0.8 * dusk.radiance[0]  # a low sun is warm


def test_night_lamps_light_the_street(noon):
    gen, _, rs, K = noon
    night = gen.frame(8, 0, FrameOverrides(weather="clear", time_of_day="night"))
    rs.update(night)
    try:
        lamp = next(f for f in night.city.furniture if f.kind == "street_light")
        R, t = look_at((lamp.center[0] + 12.0, lamp.center[1] - 12.0, 10.0), (lamp.center[0], lamp.center[1], 0.0))
        lit = rs.render(Camera(K, R, t, W, H), effects=False)
        assert len(rs._light(Camera(K, R, t, W, H)).lamps) > 0
        ground = (lit.instance == 0) & np.isfinite(lit.depth)
        X, v, u = _world_points(lit.depth, K, R, t, ground)
        on = X[:, 2] < 0.3
        d = np.hypot(X[on, 0] - lamp.center[0], X[on, 1] - lamp.center[1])
        near, far = _luma(lit.rgb[v[on], u[on]])[d < 3.0], _luma(lit.rgb[v[on], u[on]])[d > 12.0]
        assert len(near) > 20 and len(far) > 20
        assert near.mean() > 1.5 * far.mean()  # a pool of light under the lamp
    finally:
        rs.update(gen.frame(8, 0, FrameOverrides(weather="clear", time_of_day="noon")))


def test_haze_is_thin_enough_to_see_cars_from_a_drone():
    """Clear air keeps >= 95% of a car's contrast over 120 m, rain >= 70%; fog is fog (visibility
    under 1 km) yet a car 100 m away keeps >= 30% of its contrast."""
    for kind, floor in (("clear", 0.95), ("overcast", 0.88), ("rain", 0.69), ("snow", 0.6)):
        assert math.exp(-_WEATHER_RANGES[kind]["fog"][1] * 120.0) >= floor, kind
    lo, hi = _WEATHER_RANGES["fog"]["fog"]
    assert 3.912 / lo <= 1000.0 and math.exp(-hi * 100.0) >= 0.3
    rng = np.random.default_rng(3)
    assert all(draw_weather(rng, {"fog": 1.0}).visibility < 1000.0 for _ in range(50))
    assert direct_sun(0.0) == 1.0 and direct_sun(0.9) == 0.0 and 0.8 < direct_sun(0.3) < 0.95


@pytest.mark.parametrize("name", [p for p in available_presets() if p != "tiny"])
def test_presets_are_mostly_clear_or_overcast_daylight(name):
    p = load_preset(name)
    kinds, times = p.weather.kinds, p.lighting.times
    share = lambda d, keys: sum(d.get(k, 0.0) for k in keys) / sum(d.values())  # noqa: E731
    assert share(kinds, ("clear", "overcast")) >= 0.75
    assert share(times, ("morning", "noon", "afternoon")) >= 0.75
    assert min(kinds.get(k, 0.0) for k in ("rain", "snow", "fog")) > 0  # a minority, not none
    assert times.get("night", 0.0) > 0 and times.get("dusk", 0.0) > 0


def test_every_ground_role_has_a_surface_and_asphalt_is_grey(noon):
    _, scene, _, _ = noon
    for role in ("road", "sidewalk", "lawn", "marking_white", "marking_yellow", "ground"):
        assert ground_surface(role, scene.city).pattern in PATTERNS
    assert ground_surface("road", scene.city).pattern == "asphalt"
    c = np.asarray(ground_material("road", scene.city, scene.weather).base_color)
    assert 0.07 < c.mean() < 0.14 and c.max() - c.min() < 0.01  # aged asphalt, grey


def test_contact_shadows_darken_the_ground_under_agents_only(noon, monkeypatch):
    """The contact-shadow quads darken pixels only on the ground around agents' footprints (the
    quad: the footprint grown by at most 0.3 m), and leave ids and depth alone."""
    gen, scene, rs, K = noon
    overcast = gen.frame(8, 0, FrameOverrides(weather="overcast", time_of_day="noon"))
    rs.update(overcast)
    try:
        car = next(a for a in overcast.agents if a.category == "car")
        R, t = look_at((car.center[0] + 6.0, car.center[1] - 6.0, 5.0), (car.center[0], car.center[1], 0.0))
        # the camera's automatic exposure held: a frame the shadows darken is opened up a little
        # (as a camera does), which would brighten every other pixel by a grey level
        from omnigen.scenes import gl_raster
        monkeypatch.setattr(gl_raster, "auto_exposure", lambda rgb, max_gain: rgb)
        with_ = rs.render(Camera(K, R, t, W, H))
        monkeypatch.setattr(raster, "CONTACT_SHADOW", 0.0)
        without = rs.render(Camera(K, R, t, W, H))
        assert np.array_equal(with_.instance, without.instance) and np.array_equal(with_.depth, without.depth)
        darker = _luma(with_.rgb) < _luma(without.rgb) - 3.0
        assert darker.sum() > 20 and (_luma(with_.rgb) <= _luma(without.rgb) + 0.5).all()
        # pixels on a silhouette (an awning's edge over the footway) are antialiased in colour,
        # so part of one may be ground the id pass's depth does not name: judged inside surfaces
        z = np.where(np.isfinite(with_.depth), with_.depth, 1e4)
        pad = np.pad(z, 1, mode="edge")
        near = np.stack([pad[1 + dy:pad.shape[0] - 1 + dy, 1 + dx:pad.shape[1] - 1 + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)])
        inner = (near.max(axis=0) - near.min(axis=0)) < 0.5
        X, _, _ = _world_points(with_.depth, K, R, t, darker & inner & np.isfinite(with_.depth))
        quads = []
        for a in overcast.agents:
            grow = min(0.3, 0.25 * min(a.dims[0], a.dims[1])) + 0.05
            c, s = math.cos(a.yaw), math.sin(a.yaw)
            hl, hw = a.dims[0] / 2 + grow, a.dims[1] / 2 + grow
            quads.append(Polygon([(a.center[0] + c * x - s * y, a.center[1] + s * x + c * y)
                                  for x, y in ((-hl, -hw), (hl, -hw), (hl, hw), (-hl, hw))]))
        inside = [any(q.contains(Point(x[0], x[1])) for q in quads) for x in X]
        assert np.mean(inside) > 0.98
    finally:
        rs.update(gen.frame(8, 0, FrameOverrides(weather="clear", time_of_day="noon")))


def test_street_canyon_sky_view_follows_height_over_width():
    """Oke's canyon-floor sky view cos(atan(2 H / W)) from median heights and widths, floored."""
    from types import SimpleNamespace as NS

    def city(h, road, walk):
        parts = (NS(top_z=h),)
        return NS(buildings=[NS(parts=parts)] * 3, roads=[NS(width=road)] * 2,
                  sidewalks=[NS(kind="sidewalk", width=walk), NS(kind="plaza", width=50.0)])

    h, svf, w = raster.street_canyon(city(40.0, 20.0, 4.0))
    assert (h, w) == (40.0, 28.0) and svf == pytest.approx(math.cos(math.atan(80.0 / 28.0)))
    assert raster.street_canyon(city(8.0, 20.0, 4.0))[1] > 0.8  # low houses: most of the sky
    assert raster.street_canyon(city(200.0, 10.0, 2.0))[1] == raster.MIN_SKY_VIEW
    assert raster.street_canyon(NS(buildings=[], roads=[], sidewalks=[])) == (0.0, 1.0, 1.0)


def test_sky_view_map_sees_buildings_around_a_cell():
    """A tower hides sky from the street beside it, not from its own roof or from far away."""
    from types import SimpleNamespace as NS

    tower = NS(footprint=((0.0, 0.0), (20.0, 0.0), (20.0, 20.0), (0.0, 20.0)), top_z=60.0, roof_height=0.0)
    city = NS(bounds=(-100.0, -100.0, 100.0, 100.0), buildings=[NS(parts=(tower,))])
    svf, (x0, y0, inv_side, cell) = raster.sky_view_map(city)
    assert svf.shape[0] == svf.shape[1] and inv_side == pytest.approx(1.0 / (svf.shape[0] * cell))
    at = lambda x, y: svf[int((y - y0) / cell), int((x - x0) / cell)]  # noqa: E731
    assert at(10.0, 10.0) == pytest.approx(1.0)  # the roof: nothing higher
    assert at(25.0, 10.0) < 0.85  # the street beside it: a wall 60 m high 5 m away hides a side
    assert at(-90.0, -90.0) > 0.98 and at(-90.0, -90.0) > at(25.0, 10.0)
    assert at(40.0, 10.0) > at(25.0, 10.0)  # further off, more sky


def test_canyon_floor_gets_less_sky_than_the_roofs(noon, monkeypatch):
    """Overcast (sky light only): with the sky-view map, ground the buildings hide sky from loses
    more of its light than open ground does (the exposure scales both alike); ids and depth are
    untouched."""
    gen, scene, rs, K = noon
    overcast = gen.frame(8, 0, FrameOverrides(weather="overcast", time_of_day="noon"))
    rs.update(overcast)
    try:
        R, t = look_at((-5.0, -45.0, 60.0), (0.0, 0.0, 0.0))
        assert rs._canyon[0] > 0 and rs._svf.min() < 0.8
        canyon = rs.render(Camera(K, R, t, W, H), effects=False)
        svf = rs._svf
        monkeypatch.setattr(rs, "_canyon", (0.0, 1.0, 1.0))
        monkeypatch.setattr(rs, "_svf", np.ones((1, 1), dtype=np.float32))
        rs.gl.set_sky_view(rs._svf)
        try:
            open_ = rs.render(Camera(K, R, t, W, H), effects=False)
        finally:
            rs.gl.set_sky_view(svf)
        assert np.array_equal(canyon.instance, open_.instance) and np.array_equal(canyon.depth, open_.depth)
        seen = np.isfinite(canyon.depth) & (_luma(open_.rgb) > 20.0)
        X, v, u = _world_points(canyon.depth, K, R, t, seen)
        ratio = (_luma(canyon.rgb) / np.maximum(_luma(open_.rgb), 1.0))[v, u]
        x0, y0, _, cell = rs._svf_xform
        n = svf.shape[0]
        g = svf[np.clip(((X[:, 1] - y0) / cell).astype(int), 0, n - 1), np.clip(((X[:, 0] - x0) / cell).astype(int), 0, n - 1)]
        ground = X[:, 2] < 0.5
        hidden, open_sky = ratio[ground & (g < 0.75)], ratio[ground & (g > 0.97)]
        assert len(hidden) > 30 and len(open_sky) > 30
        assert np.median(hidden) < 0.95 * np.median(open_sky)  # sRGB: the linear loss, to the power 1/2.2
    finally:
        rs.update(gen.frame(8, 0, FrameOverrides(weather="clear", time_of_day="noon")))
