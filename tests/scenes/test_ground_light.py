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
