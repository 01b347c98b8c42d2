"""Issue 48: BlenderScene.update changes what changes and makes no datablock beyond its bounds.

Frames over the tiny city through rain at night, snow, fog and a clear noon: once the agent pool
has grown to the most agents a frame had, every further update keeps the very same objects,
materials, lights, images, node groups and worlds, and meshes but for agent meshes of new shapes
up to the mesh pool's bound (no per-frame creation, nothing removed), and shows exactly the
frame's agents, lamps and weather. An agent mesh lent to an agent of its shape and moved to its
vertices holds what a mesh built new for that agent holds, normals included.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from omnigen.scenes.generate import FrameOverrides, SceneGenerator

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")
blender = pytest.importorskip("omnigen.scenes.blender_backend", reason="bpy not installed")

SEED = 21
WEATHERS = (("rain", "night"), ("clear", "noon"), ("snow", "dusk"), ("fog", "noon"))
KINDS = ("meshes", "objects", "materials", "lights", "images", "node_groups", "worlds")


def _datablocks() -> dict[str, set[int]]:
    import bpy

    return {kind: {block.as_pointer() for block in getattr(bpy.data, kind)} for kind in KINDS}


@pytest.fixture(scope="module")
def frames():
    gen = SceneGenerator("tiny", SEED)
    return [gen.frame(SEED, i, FrameOverrides(weather=w, time_of_day=t)) for i, (w, t) in enumerate(WEATHERS)]


def test_updates_reuse_every_datablock_and_show_only_the_frame(frames):
    bs = blender.BlenderScene(frames[0])
    for scene in frames[1:]:  # the pool grows to the most agents a frame has
        bs.update(scene)
    made = _datablocks()
    pool = bs._agent_meshes
    for scene in frames:
        bs.update(scene)
        now = _datablocks()
        assert {k: v for k, v in now.items() if k != "meshes"} == {k: v for k, v in made.items() if k != "meshes"}
        assert made["meshes"] <= now["meshes"]  # none removed; new ones are agent meshes within the bound
        assert len(now["meshes"] - made["meshes"]) <= len(pool.meshes) <= math.ceil(blender.POOL_SHARE * pool.most)
        shown = bs.objects_summary()
        assert sorted(o["name"] for o in shown if o["instance_id"]) == sorted(a.name for a in scene.agents)
        assert {o["instance_id"] for o in shown if o["instance_id"]} == {a.instance_id for a in scene.agents}
        env = bs.environment_objects()
        roles = {o["name"]: o["role"] for o in env}
        lamps = sum(f.kind == "street_light" for f in scene.city.furniture) if scene.lighting.street_lights_on else 0
        assert list(roles.values()).count("lamp") == lamps and len(env) == len(roles)
        w = scene.weather
        assert (blender.FOG in roles) == (w.fog_density > 0)
        falls = w.precipitation > 0 and w.kind in ("rain", "snow")
        assert roles.get(blender.PRECIPITATION) == (w.kind if falls else None)
    assert max(len(s.agents) for s in frames) > min(len(s.agents) for s in frames)  # slots were hidden too


def test_a_mesh_is_repainted_only_where_a_material_changed(frames):
    import bpy

    scene = frames[0]
    obj = next(o for o in blender.compile_scene(scene) if o.kind == "building")
    mesh = bpy.data.meshes.new("omnigen_test_paint")
    try:
        painted = blender._paint_mesh(mesh, obj.parts, {role: blender.Surface() for role in obj.parts})
        assert painted.paint(obj.materials) and not painted.paint(dict(obj.materials))
        role = next(iter(obj.materials))
        recolored = {**obj.materials, role: blender.replace(obj.materials[role], base_color=(0.1, 0.2, 0.3))}
        assert painted.paint(recolored)
        base = np.empty(3 * len(mesh.polygons), dtype=np.float32)
        mesh.attributes["pbr_base"].data.foreach_get("vector", base)
        first = np.repeat(np.arange(len(obj.parts)), [len(p.faces) for p in obj.parts.values()]) == 0
        assert np.allclose(base.reshape(-1, 3)[first], (0.1, 0.2, 0.3))
    finally:
        bpy.data.meshes.remove(mesh)


_ATTRIBUTE_KINDS = {"FLOAT_VECTOR": ("vector", 3, np.float32), "BOOLEAN": ("value", 1, bool), "INT": ("value", 1, np.int32),
                    "INT32_2D": ("value", 2, np.int32), "FLOAT": ("value", 1, np.float32), "FLOAT_COLOR": ("color", 4, np.float32)}


def _mesh_bytes(mesh) -> dict:
    """Every attribute of `mesh` but selection (Blender's calc_edges leaves edge selection
    uninitialised: two identical builds differ there), its edges, loops and faces, as bytes."""
    out = {"counts": (len(mesh.vertices), len(mesh.edges), len(mesh.loops), len(mesh.polygons))}
    for attr in mesh.attributes:
        if not attr.name.startswith(".select"):
            field, width, dtype = _ATTRIBUTE_KINDS[attr.data_type]
            values = np.zeros(len(attr.data) * width, dtype)
            attr.data.foreach_get(field, values)
            out[(attr.name, attr.domain, attr.data_type)] = values.tobytes()
    for items, field, width in ((mesh.edges, "vertices", 2), (mesh.loops, "vertex_index", 1), (mesh.loops, "edge_index", 1),
                                (mesh.polygons, "loop_start", 1), (mesh.polygons, "loop_total", 1)):
        values = np.zeros(len(items) * width, np.int32)
        items.foreach_get(field, values)
        out[field] = values.tobytes()
    return out


def test_triangles_written_through_attributes_equal_the_collection_writes(frames):
    """_set_triangles writes positions and corner vertices through their attributes (a tenth of
    the cost); the mesh must be the one the vertices'/loops' own foreach_set made, new or reused."""
    import bpy

    reused = bpy.data.meshes.new("omnigen_test_reused")
    made = []
    try:
        for obj in blender.compile_scene(frames[0]):
            v, f, _ = blender._stack_parts(obj.parts)
            plain, fast = bpy.data.meshes.new("omnigen_test_plain"), bpy.data.meshes.new("omnigen_test_fast")
            made += [plain, fast]
            plain.vertices.add(len(v))
            plain.vertices.foreach_set("co", v.ravel())
            plain.loops.add(3 * len(f))
            plain.loops.foreach_set("vertex_index", f.ravel())
            plain.polygons.add(len(f))
            plain.polygons.foreach_set("loop_start", np.arange(0, 3 * len(f), 3, dtype=np.int32))
            plain.update(calc_edges=True)
            blender._set_triangles(fast, v, f)
            blender._set_triangles(reused, v, f)
            want = _mesh_bytes(plain)
            assert _mesh_bytes(fast) == want and _mesh_bytes(reused) == want, obj.name
    finally:
        for mesh in made + [reused]:
            bpy.data.meshes.remove(mesh)


def test_stacked_parts_are_the_parts_converted_and_stacked(frames):
    for obj in blender.compile_scene(frames[1]):
        v, f, order = blender._stack_parts(obj.parts)
        parts = list(obj.parts.values())
        offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
        assert v.dtype == np.float32 and f.dtype == np.int32
        assert v.tobytes() == np.vstack([np.asarray(p.vertices, dtype=np.float32) for p in parts]).tobytes()
        assert f.tobytes() == np.vstack([np.asarray(p.faces, dtype=np.int32) + o for p, o in zip(parts, offsets)]).tobytes()
        assert order == [(role, len(p.faces)) for role, p in obj.parts.items()]


def _normals(mesh) -> dict[str, bytes]:
    out = {}
    for name in ("vertex_normals", "polygon_normals", "corner_normals"):
        items = getattr(mesh, name)
        values = np.zeros(3 * len(items), np.float32)
        items.foreach_get("vector", values)
        out[name] = values.tobytes()
    return out


def _same_shape_pairs(frames):
    """(agent of one frame, agent of another) pairs of one shape and other vertex positions."""
    seen, pairs = {}, []
    for scene in frames:
        for obj in blender.compile_scene(scene):
            if obj.kind != "agent":
                continue
            v, f, order = blender._stack_parts(obj.parts)
            key = blender._shape(v, f, order,
                                 blender._looks({role: blender.part_surface("agent", role, scene.city) for role in obj.parts}))
            first = seen.setdefault(key, obj)
            if first is not obj and not np.array_equal(blender._stack_parts(first.parts)[0], v):
                pairs.append((first, obj))
    return pairs


def test_a_mesh_moved_to_an_agent_of_its_shape_equals_one_built_for_it(frames):
    import bpy

    pairs = _same_shape_pairs(frames)
    assert len(pairs) >= 3
    made = []
    try:
        for first, other in pairs[:8]:
            surfaces = {role: blender.Surface() for role in first.parts}
            moved, new = bpy.data.meshes.new("omnigen_test_moved"), bpy.data.meshes.new("omnigen_test_new")
            made += [moved, new]
            blender._paint_mesh(moved, first.parts, surfaces)
            _normals(moved)  # computed for the first positions: moving the vertices must make them stale
            blender._set_positions(moved, blender._stack_parts(other.parts)[0])
            blender._paint_mesh(new, other.parts, surfaces)
            assert _mesh_bytes(moved) == _mesh_bytes(new), other.name
            assert _normals(moved) == _normals(new), other.name
    finally:
        for mesh in made:
            bpy.data.meshes.remove(mesh)


def test_agents_take_kept_meshes_of_their_shape(frames):
    """The pool lends kept meshes: over frames whose agents share shapes, most agents after the
    first frame take a mesh moved to their vertices, and each shown slot holds its agent's
    vertices."""
    bs = blender.BlenderScene(frames[0])
    pool = bs._agent_meshes
    for scene in frames[1:] + frames[:2]:
        bs.update(scene)
    assert pool.moved > 0 and pool.built < sum(len(s.agents) for s in frames[1:] + frames[:2])
    agents = [o for o in blender.compile_scene(frames[1]) if o.kind == "agent"]
    for bobj, obj in zip(bs._slots, agents):
        v = np.zeros(3 * len(bobj.data.vertices), np.float32)
        bobj.data.attributes["position"].data.foreach_get("vector", v)
        assert v.tobytes() == blender._stack_parts(obj.parts)[0].tobytes(), obj.name
    assert all(bobj.data.name == "omnigen_agent_none" for bobj in bs._slots[len(agents):])


def test_each_slot_is_labelled_as_its_agent_after_any_frames(frames):
    """A slot's index and properties are written only when they change: after frames in any order
    each shown slot still names its own agent (pass index, instance id, category, dims, kind), and
    each hidden one index 0."""
    bs = blender.BlenderScene(frames[0])
    hidden = 0
    for scene in frames[1:] + frames[::-1]:
        bs.update(scene)
        agents = [o for o in blender.compile_scene(scene) if o.kind == "agent"]
        hidden += len(bs._slots) - len(agents)
        for bobj, obj in zip(bs._slots, agents):
            assert (bobj.pass_index, bobj["omnigen_instance_id"], bobj["omnigen_category"], bobj["omnigen_kind"]) == \
                (obj.instance_id, obj.instance_id, obj.category, "agent"), obj.name
            assert list(bobj["omnigen_dims"]) == [float(d) for d in obj.dims], obj.name
        assert all(bobj.pass_index == 0 and bobj["omnigen_instance_id"] == 0 for bobj in bs._slots[len(agents):])
    assert hidden > 0  # the frames differ in their agents' number: some slots were hidden after showing one
