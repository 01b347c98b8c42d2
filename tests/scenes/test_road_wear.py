"""What traffic leaves on the roads (scenes/road_wear.py and the raster shader's asphalt): oil along
each lane's middle, darkest where vehicles queue before a stop line, two wheel tracks a lane, the
gutters; in snow, the wheel tracks cleared down to wet asphalt."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnigen.camera import Camera, intrinsics_from_fov, look_at
from omnigen.scenes.generate import FrameOverrides
from omnigen.scenes.layout import build_city
from omnigen.scenes.preset import load_preset
from omnigen.scenes.road_wear import TRACK_HALF, road_wear_map

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture(scope="module")
def city():
    return build_city(load_preset("tiny"), 8)


def _at(wear, xform, x, y):
    """The map's (stain, tracks) in [0, 1] at world (x, y) (nearest cell)."""
    x0, y0, sx, sy = xform
    ny, nx = wear.shape[:2]
    i, j = int((x - x0) * sx * nx), int((y - y0) * sy * ny)
    return wear[j, i] / 255.0


def _lane_point(lane, along: float, across: float):
    h = np.array([math.cos(lane.heading), math.sin(lane.heading)])
    return np.asarray(lane.start) + along * h + across * np.array([-h[1], h[0]])


def _approach(city):
    """A driving lane and the distance along it of a stop line across it."""
    for m in (m for m in city.markings if m.kind == "stop_line"):
        for lane in (ln for road in city.roads for ln in road.lanes if ln.kind == "driving"):
            h = np.array([math.cos(lane.heading), math.sin(lane.heading)])
            d = np.asarray(m.center) - np.asarray(lane.start)
            across = float(d @ np.array([-h[1], h[0]]))
            if math.cos(lane.heading - m.yaw) > 0.999 and abs(across) < m.width / 2.0:
                along = float(d @ h)
                if along > 60.0:
                    return lane, along
    raise AssertionError("no stop line with 60 m of lane before it")


def test_the_map_is_the_citys_own_and_the_same_every_time(city):
    a, xa = road_wear_map(city)
    b, xb = road_wear_map(build_city(load_preset("tiny"), 8))
    assert a.dtype == np.uint8 and a.shape[2] == 2 and xa == xb and np.array_equal(a, b)
    other, _ = road_wear_map(build_city(load_preset("tiny"), 9))
    assert other.shape != a.shape or not np.array_equal(other, a)  # another city, other roads


def test_oil_runs_down_the_lane_middle_darkest_before_the_stop_line_and_wheels_run_beside_it(city):
    wear, xform = road_wear_map(city)
    lane, stop = _approach(city)
    near = _at(wear, xform, *_lane_point(lane, stop - 4.0, 0.0))
    far = _at(wear, xform, *_lane_point(lane, stop - 60.0, 0.0))
    beside = _at(wear, xform, *_lane_point(lane, stop - 60.0, 0.55))
    track = _at(wear, xform, *_lane_point(lane, stop - 60.0, TRACK_HALF))
    assert near[0] > 0.85 and 0.3 < far[0] < 0.6 and beside[0] < 0.5 * far[0]  # the middle band, queue strongest
    assert track[1] > 0.9 and near[1] < 0.1  # tracks beside the middle, not on it
    # nothing off the roads: the centre of a building's footprint
    b = np.asarray(city.buildings[0].parts[0].footprint).mean(axis=0)
    assert not _at(wear, xform, *b).any()


@pytest.fixture
def snow_raster(noon_raster):
    """The tiny preset's city (tests/scenes/conftest.py) under full snow at noon; back to its clear
    noon after the test."""
    from dataclasses import replace

    gen, clear, rs = noon_raster
    scene = gen.frame(8, 0, FrameOverrides(weather="snow", time_of_day="noon"))
    scene = replace(scene, weather=replace(scene.weather, snow_cover=1.0))
    rs.update(scene)
    yield scene, rs
    rs.update(clear)


def test_in_snow_the_wheel_tracks_show_the_asphalt(snow_raster):
    """Looking straight down on a lane in snow: the pixels over its wheel tracks are darker than
    the snow between them, by far; with a blank map (no traffic) the lane is evenly white."""
    scene, rs = snow_raster
    lane, stop = _approach(scene.city)
    size = 160
    K = intrinsics_from_fov(math.radians(30), size, size)
    target = np.append(_lane_point(lane, stop - 40.0, 0.0), 0.0)
    R, t = look_at(target + [0.0, 0.01, 12.0], target)
    cam = Camera(K, R, t, size, size)

    def luma_at(frame, across):
        p = np.append(_lane_point(lane, stop - 40.0, across), 0.0)
        q = K @ (R @ p + t)
        u, v = int(round(q[0] / q[2])), int(round(q[1] / q[2]))
        return float(frame.rgb[v - 1:v + 2, u - 1:u + 2].astype(np.float64).mean())

    worn = rs.render(cam, effects=False)
    wear, _ = road_wear_map(scene.city)
    try:
        rs.gl.make_current()
        rs.gl.set_road_wear(np.zeros_like(wear))
        blank = rs.render(cam, effects=False)
    finally:
        rs.gl.make_current()
        rs.gl.set_road_wear(wear)
    assert luma_at(worn, TRACK_HALF) < luma_at(worn, 0.0) - 40.0  # a dark track beside the white middle
    assert luma_at(worn, -TRACK_HALF) < luma_at(worn, 0.0) - 40.0
    assert abs(luma_at(blank, TRACK_HALF) - luma_at(blank, 0.0)) < 10.0
    assert np.array_equal(worn.rgb, rs.render(cam, effects=False).rgb)  # deterministic


def test_a_partial_snow_cover_lies_in_patches_and_none_without_cover(noon_raster):
    """Ground points are either under snow or bare (the cover is the snow's share of the area, not
    a grey wash over everything), more of them under snow as the cover grows; a cover of 0 leaves
    the frame exactly as in clear weather."""
    from dataclasses import replace

    _, scene, rs = noon_raster
    size = 160
    K = intrinsics_from_fov(math.radians(60), size, size)
    R, t = look_at((0.0, -30.0, 45.0), (0.0, 0.0, 0.0))
    cam = Camera(K, R, t, size, size)

    def frame(cover):
        rs.update(replace(scene, weather=replace(scene.weather, kind="snow", snow_cover=cover)))
        return rs.render(cam, effects=False)

    try:
        clear = rs.render(cam, effects=False)
        frames = {c: frame(c) for c in (0.0, 0.3, 0.5, 1.0)}
    finally:
        rs.update(scene)
    assert np.array_equal(frames[0.0].rgb, clear.rgb)
    luma = {c: f.rgb.astype(np.float64) @ (0.299, 0.587, 0.114) for c, f in frames.items()}
    v, u = np.nonzero((clear.instance == 0) & np.isfinite(clear.depth))
    z = clear.depth[v, u]
    X = (np.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], axis=1) - t) @ R
    span = luma[1.0][v, u] - luma[0.0][v, u]
    keep = (X[:, 2] < 0.3) & (span > 40.0)  # the ground (not roofs), where snow shows
    assert keep.sum() > 2000
    share = {}
    for c in (0.3, 0.5):
        f = (luma[c][v, u] - luma[0.0][v, u])[keep] / span[keep]  # 0: bare, 1: as under full cover
        assert ((f > 0.25) & (f < 0.75)).mean() < 0.1  # snow or bare ground, hardly anything between
        share[c] = (f >= 0.75).mean()
    assert 0.15 < share[0.3] < share[0.5] < 0.85
