"""scenes/blender_backend: the bpy scene matches the description and the raster backend object
for object; frame updates do not leak; the sky faces the right way; .blend files are written."""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnigen.scenes.generate import FrameOverrides, SceneGenerator

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
blender = pytest.importorskip("omnigen.scenes.blender_backend", reason="bpy not installed")


@pytest.fixture(scope="module")
def built():
    gen = SceneGenerator("tiny", 21)
    scene = gen.frame(21, 0, FrameOverrides(weather="rain", time_of_day="night"))
    return gen, scene, blender.BlenderScene(scene)


def by_name(summary):
    return {o["name"]: o for o in summary}


def test_agents_match_the_description(built):
    _, scene, bs = built
    objs = by_name(bs.objects_summary())
    for a in scene.agents:
        o = objs[a.name]
        assert o["instance_id"] == a.instance_id and o["category"] == a.category
        assert np.allclose(o["center"], a.center, atol=2e-4), a.name  # float32 meshes
        assert np.allclose(o["dims"], a.dims, atol=2e-4), a.name
        assert math.isclose(math.remainder(o["yaw"] - a.yaw, 2 * math.pi), 0.0, abs_tol=1e-5)


def test_both_backends_build_the_same_objects(built):
    raster = pytest.importorskip("omnigen.scenes.raster_backend")
    _, scene, bs = built
    try:
        rs = raster.RasterScene(scene)
    except Exception as exc:
        pytest.skip(f"no headless GL: {exc}")
    b, r = by_name(bs.objects_summary()), by_name(rs.objects_summary())
    assert set(b) == set(r)
    assert len(b) > len(scene.agents) + len(scene.city.buildings)  # static objects too
    for name in b:
        assert b[name]["instance_id"] == r[name]["instance_id"] and b[name]["category"] == r[name]["category"]
        assert np.allclose(b[name]["center"], r[name]["center"], atol=5e-4), name
        assert np.allclose(b[name]["dims"], r[name]["dims"], atol=5e-4), name


def test_frame_updates_replace_agents_without_leaks(built):
    gen, scene, bs = built
    counts, slots = [], len(scene.agents)
    for i in (1, 2, 3, 4):
        frame = gen.frame(21, i, FrameOverrides(weather="rain", time_of_day="night"))
        bs.update(frame)
        assert {o["name"] for o in bs.objects_summary() if o["instance_id"]} == {a.name for a in frame.agents}
        c = bs.datablock_counts()
        slots = max(slots, len(frame.agents))  # the agent pool: as many objects as the most agents a frame had
        kept = bs._agent_meshes  # agent meshes kept by shape, within their bound, and the empty one of hidden slots
        assert len(kept.meshes) <= math.ceil(blender.POOL_SHARE * kept.most)
        counts.append((c["meshes"] - len(kept.meshes) - 1, c["objects"] - slots, c["materials"], c["lights"], c["images"]))
    assert len(set(counts)) == 1, counts  # everything but the agent pools stays exactly as many
    bs.update(scene)


def test_environment_follows_the_description(built):
    _, scene, bs = built
    env = bs.environment_objects()
    roles = [o["role"] for o in env]
    assert scene.lighting.street_lights_on
    assert roles.count("lamp") == sum(f.kind == "street_light" for f in scene.city.furniture)
    assert "rain" in roles and "fog" in roles and "sun" in roles
    bs.place_weather((5.0, -3.0, 1.6))
    fog = next(o for o in bs.environment_objects() if o["role"] == "fog")
    assert fog["location"][:2] == pytest.approx((5.0, -3.0))


def test_sky_sun_points_where_the_description_says():
    for az in (0.0, 90.0, 225.0):
        got = blender.sky_sun_azimuth_probe(12.0, az)
        assert abs(math.remainder(got - az, 360.0)) <= 7.5, (az, got)


def test_save_blend(built, tmp_path):
    _, _, bs = built
    path = bs.save_blend(tmp_path / "city.blend")
    assert path.exists() and path.stat().st_size > 50_000
