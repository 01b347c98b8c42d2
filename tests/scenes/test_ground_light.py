"""The raster preview's light from the ground (raster_backend.illumination): a street canyon's floor
returns less light to the faces above it than open ground does, in proportion to the sky it sees.
Pure numpy on a generated scene; no GL context needed."""

from __future__ import annotations

import numpy as np
import pytest

from omnigen.scenes.generate import FrameOverrides, SceneGenerator

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

raster = pytest.importorskip("omnigen.scenes.raster_backend", reason="pyrender/PyOpenGL not installed")


def test_a_canyon_floor_returns_ground_light_by_its_sky_view():
    scene = SceneGenerator("tiny", 8).frame(8, 0, FrameOverrides(weather="clear", time_of_day="noon"))
    e_sun, e_sky = raster.daylight(scene)
    open_ground = raster.illumination(scene, 1.0)
    canyon = raster.illumination(scene, 0.4)
    # open ground: its albedo times the whole daylight (the warm tint's green is 0.95)
    assert open_ground.ground_ambient[1] == pytest.approx(0.95 * raster.GROUND_ALBEDO * (e_sun + e_sky))
    assert np.allclose(canyon.ground_ambient, 0.4 * np.asarray(open_ground.ground_ambient))
    assert np.allclose(canyon.sky_ambient, open_ground.sky_ambient)  # the sky's own light is the shader's svf map's


def _wall(abc, cos_phi):
    a, b, c = abc
    return a + b * cos_phi + c * cos_phi * cos_phi


def test_walls_facing_away_from_a_clear_suns_sky_get_less_of_it():
    clear = raster.sky_on_walls(35.0, 0.0)
    # the CIE clear sky, sun 35 degrees up: a wall facing away 0.38, at right angles 0.54, facing it 1.15
    assert _wall(clear, -1.0) == pytest.approx(0.38, abs=0.01)
    assert _wall(clear, 0.0) == pytest.approx(0.54, abs=0.01)
    assert _wall(clear, 1.0) == pytest.approx(1.15, abs=0.02)
    # a high sun's bright region is near the zenith: walls differ little by azimuth, all near 0.45
    high = [_wall(raster.sky_on_walls(80.0, 0.0), c) for c in (-1.0, 0.0, 1.0)]
    assert max(high) - min(high) < 0.15 and high[1] < 0.5
    # overcast (and twilight): the CIE overcast sky's 0.397, the same whatever the azimuth
    assert raster.sky_on_walls(35.0, 1.0) == pytest.approx((raster.CIE_OVERCAST_WALL, 0.0, 0.0))
    assert raster.sky_on_walls(-5.0, 0.0) == pytest.approx((raster.CIE_OVERCAST_WALL, 0.0, 0.0))
    half = raster.sky_on_walls(35.0, 0.5)
    assert np.allclose(half, 0.5 * np.asarray(clear) + 0.5 * np.array([raster.CIE_OVERCAST_WALL, 0.0, 0.0]))


def test_the_aureole_round_a_clear_sun_is_a_seventh_of_the_skys_light_and_none_when_overcast():
    # the CIE clear sky within 15 degrees of the sun: 0.14-0.15 of its light on a roof, sun above 25 degrees
    assert all(0.14 <= raster.aureole_share(e, 0.0) <= 0.15 for e in (25.0, 45.0, 70.0))
    assert raster.aureole_share(45.0, 1.0) == 0.0 and raster.aureole_share(-3.0, 0.0) == 0.0
    assert raster.aureole_share(45.0, 0.4) == pytest.approx(0.6 * raster.aureole_share(45.0, 0.0))
    scene = SceneGenerator("tiny", 8).frame(8, 0, FrameOverrides(weather="clear", time_of_day="noon"))
    light = raster.illumination(scene)
    assert light.aureole == pytest.approx(raster.aureole_share(scene.lighting.sun_elevation, scene.weather.cloud_cover))
