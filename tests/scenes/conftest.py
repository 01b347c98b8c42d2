"""Fixtures shared by the scene tests."""

from __future__ import annotations

import math
from typing import Callable

import pytest
from shapely.geometry import Polygon

from omnigen.camera import Camera, intrinsics_from_fov, look_at
from omnigen.scenes.generate import FrameOverrides, SceneGenerator
from omnigen.scenes.shapes import rect_polygon

PROBE_SIZE = 160


def _footprint(agent) -> Polygon:
    return rect_polygon(agent.center[:2], agent.dims[0], agent.dims[1], agent.yaw)


@pytest.fixture(scope="session")
def footprint() -> Callable[..., Polygon]:
    """The function giving an agent's annotated footprint on the ground (its cuboid's l x w
    rectangle at its yaw), which the placement checks compare with each other and with obstacles."""
    return _footprint


@pytest.fixture(scope="module")
def noon_raster():
    """(generator, scene, RasterScene) of the tiny preset's first frame of seed 8 at a clear noon,
    once per test module. A probe frame (160 x 160, 60 degrees, from above the city's south side)
    is rendered first, so a machine without headless GL skips with the reason rather than failing
    obscurely in the first test."""
    raster = pytest.importorskip("omnigen.scenes.raster_backend", reason="pyrender/PyOpenGL not installed")
    gen = SceneGenerator("tiny", 8)
    scene = gen.frame(8, 0, FrameOverrides(weather="clear", time_of_day="noon"))
    try:
        rs = raster.RasterScene(scene)
        K = intrinsics_from_fov(math.radians(60), PROBE_SIZE, PROBE_SIZE)
        rs.render(Camera(K, *look_at((0.0, -40.0, 30.0), (0.0, 0.0, 0.0)), PROBE_SIZE, PROBE_SIZE))
    except Exception as exc:  # no headless GL here
        pytest.skip(f"headless EGL rendering unavailable: {exc}")
    yield gen, scene, rs
    rs.close()
