"""Street trees shade the ground in the raster preview: their crowns are in the sun's shadow pass
(scenes/raster_backend.py leaves out only parts lying on other faces), so the ground where a crown
blocks the sun is darker than with no shadow pass at all."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnigen.camera import Camera, intrinsics_from_fov, look_at

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")

raster = pytest.importorskip("omnigen.scenes.raster_backend", reason="pyrender/PyOpenGL not installed")


def test_tree_crowns_cast_shadows_on_the_ground(noon_raster, monkeypatch):
    _, scene, rs = noon_raster  # tests/scenes/conftest.py: the tiny preset at a clear noon
    sun = np.asarray(scene.lighting.sun_direction, dtype=np.float64)  # towards the sun
    trees = [f for f in scene.city.furniture if f.kind == "tree"]
    assert trees and sun[2] > 0.3
    size = 96
    K = intrinsics_from_fov(math.radians(40), size, size)
    ratios = []
    for f in trees:
        base = f.center[2] - f.dims[2] / 2.0
        crown = np.array([f.center[0], f.center[1], base + (f.params["trunk_height"] + f.dims[2]) / 2.0])
        ground = crown - (crown[2] - base) / sun[2] * sun  # where the crown's centre throws its shadow
        R, t = look_at(ground + [0.0, 0.01, 20.0], ground)
        cam = Camera(K, R, t, size, size)
        q = K @ (R @ ground + t)
        u, v = int(round(q[0] / q[2])), int(round(q[1] / q[2]))
        with monkeypatch.context() as m:
            shaded = rs.render(cam, effects=False).rgb
            m.setattr(raster, "MIN_SUN_SHARE", 2.0)  # no shadow pass
            plain = rs.render(cam, effects=False).rgb
        luma = [float(img[v - 1:v + 2, u - 1:u + 2].astype(np.float64).mean()) for img in (shaded, plain)]
        ratios.append(luma[0] / max(luma[1], 1.0))
    assert np.median(ratios) < 0.7  # in the crown's shade, most of the sunlight is gone
