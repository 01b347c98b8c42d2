"""Issue 48: a frame's agents and its static materials are built once per frame, whoever asks
(scenes/meshes.py frame_agent, frame_statics), and the agent mesh cache holds a whole frame's
agents (scenes/assets/build.py hold_agents).

A Cycles render asks for every agent in its Blender scene (compile_scene) and again, per camera,
for those in view in its GL labels (RasterScene._prepare_agents); both must get the very same
objects, built once. The cache, sized to the largest frame, must not evict a frame's early agents
while the frame builds its later ones (the fixed 256 entries did, against downtown's ~400).
"""

from __future__ import annotations

import math

import pytest

from omnigen.scenes import meshes
from omnigen.scenes.assets import build
from omnigen.scenes.description import AssetSpec
from omnigen.scenes.generate import SceneGenerator


@pytest.fixture(scope="module")
def two_frames():
    gen = SceneGenerator("tiny", 5)
    return gen.frame(5, 0), gen.frame(5, 1)


def test_compile_scene_and_frame_agent_share_one_object_per_agent(two_frames, monkeypatch):
    scene, _ = two_frames
    built = []
    real = meshes.agent_object
    monkeypatch.setattr(meshes, "agent_object", lambda a, s: built.append(a.name) or real(a, s))
    agents = [o for o in meshes.compile_scene(scene) if o.kind == "agent"]
    again = [o for o in meshes.compile_scene(scene) if o.kind == "agent"]
    assert [o.name for o in agents] == [a.name for a in scene.agents]
    assert all(x is y for x, y in zip(agents, again))
    assert all(meshes.frame_agent(scene, k) is agents[k] for k in range(len(agents)))
    statics = [o for o in meshes.compile_scene(scene) if o.kind != "agent"]
    assert statics and all(x is y for x, y in zip(statics, meshes.frame_statics(scene)))
    assert sorted(built) == sorted(a.name for a in scene.agents)  # each agent built once


def test_a_new_frame_builds_its_own_agents(two_frames):
    first, second = two_frames
    a = meshes.frame_agent(first, 0)
    b = meshes.frame_agent(second, 0)
    assert a is not b and b.name == second.agents[0].name
    assert b.matrix_world.tolist() == meshes.agent_object(second.agents[0], second).matrix_world.tolist()
    assert meshes.frame_agent(first, 0) is not a  # only the last frame is kept: rebuilt, equal
    assert meshes.frame_agent(first, 0).materials == a.materials


def test_raster_labels_reuse_the_frames_agents(two_frames, monkeypatch):
    """The raster's agent buffer (labels of a Cycles render) builds no agent compile_scene built."""
    raster = pytest.importorskip("omnigen.scenes.raster_backend", reason="pyrender/PyOpenGL not installed")
    from omnigen.camera import Camera, intrinsics_from_fov, look_at

    scene, _ = two_frames
    try:
        rs = raster.RasterScene(scene)
    except Exception as exc:  # no headless GL here
        pytest.skip(f"no headless GL: {exc}")
    try:
        meshes.compile_scene(scene)
        real_static = meshes.static_materials
        built = []
        real = meshes.agent_object
        monkeypatch.setattr(meshes, "agent_object", lambda a, s: built.append(a.name) or real(a, s))
        x0, y0, x1, y1 = scene.city.bounds
        centre = ((x0 + x1) / 2, (y0 + y1) / 2, 0.0)
        eye = (centre[0], centre[1] - 1.0, 80.0)
        cam = Camera(intrinsics_from_fov(math.radians(90), 64, 64), *look_at(eye, centre), 64, 64)
        _, instance = rs.labels(cam)
        assert instance.max() > 0 and rs._ranges  # agents were drawn
        assert built == []
        # the static material table from the frame's static objects: none restyled again, the same table
        restyled = []
        monkeypatch.setattr(meshes, "static_materials", lambda s, o: restyled.append(o.name) or real_static(s, o))
        table = rs._static_materials(scene)
        assert restyled == []
        plain = raster.material_table([m for o in meshes.static_objects(scene.city) for m in real_static(scene, o).values()])
        assert table.tobytes() == plain.tobytes()
    finally:
        rs.close()


def test_cache_holds_a_frame_larger_than_its_minimum(monkeypatch):
    """Past _CACHE_MIN distinct agents, the frame's first is still cached once hold_agents was told."""
    monkeypatch.setattr(build, "_CACHE", type(build._CACHE)())
    monkeypatch.setattr(build, "_cache_size", [build._CACHE_MIN])
    n = build._CACHE_MIN + 20
    build.hold_agents(n)
    specs = [(AssetSpec("traffic_cone", {}), (0.4, 0.4, 0.5 + 0.001 * i)) for i in range(n)]
    first = [build.agent_parts(spec, dims)[0] for spec, dims in specs]
    assert all(build.agent_parts(spec, dims)[0] is p for (spec, dims), p in zip(specs, first))
    build.agent_parts(AssetSpec("traffic_cone", {}), (0.4, 0.4, 2.0))
    assert len(build._CACHE) == n  # bounded: the least recent left
    build.hold_agents(10)
    assert build._cache_size[0] == n  # never shrinks below the largest frame
