"""Issue 26's assets: vehicle body styles with readable fronts and backs, the new families
(tram, tricyclist, barrow), cone styles and the furniture kinds the layout places.

What is checked, and why:
- every mesh is closed and wound outward (the raster backend culls back faces: an inverted box
  would vanish), and its bounds are the drawn cuboid (the annotation is the mesh's tight box);
- the same seed gives the same bytes;
- a vehicle's front and back differ where a detector can see it: white headlights and the
  windscreen at +x, red taillights at -x, the nose lower than the tail, the windscreen more
  raked than the rear window;
- every part role has a material in both backends' rules (materials.py);
- meshes stay light (the raster preview builds every agent in view every frame).
"""

from __future__ import annotations

import zlib

import numpy as np
import pytest
import trimesh

from omnigen.scenes.assets import props
from omnigen.scenes.assets.build import agent_parts, furniture_parts
from omnigen.scenes.assets.catalog import CAR_STYLES, CONE_STYLES, PROCEDURAL_FAMILIES, SIZES, draw_asset, draw_params
from omnigen.scenes.assets.parts import bounds_of, fit_to_dims, prism_y
from omnigen.scenes.description import Agent, AssetSpec, Furniture

TIGHT = 1e-6
VEHICLES = ("car", "van", "truck", "bus", "tram")
# Triangle budgets: a car a few hundred triangles (its wheels are most of them), a tram more.
BUDGET = {"car": 900, "van": 900, "truck": 1200, "bus": 800, "tram": 1400, "pedestrian": 800, "cyclist": 2000,
          "motorcyclist": 1400, "tricyclist": 1600, "barrow": 1200, "traffic_cone": 600}


def _closed_outward(mesh) -> bool:
    m = trimesh.Trimesh(np.asarray(mesh.vertices), np.asarray(mesh.faces), process=False)
    return bool(m.is_watertight and m.is_winding_consistent and m.volume > 0)


def _draws(family: str, n: int):
    rng = np.random.default_rng(zlib.crc32(family.encode()) + 26)
    return [draw_asset(rng, family, "standing" if family == "pedestrian" and k % 2 else "") for k in range(n)]


@pytest.mark.parametrize("family", PROCEDURAL_FAMILIES)
def test_every_family_is_closed_tight_and_light(family):
    for dims, spec in _draws(family, 12):
        parts, raw = agent_parts(spec, dims)
        lo, hi = bounds_of(parts)
        assert np.allclose(hi - lo, dims, atol=TIGHT) and np.allclose((hi + lo) / 2, 0.0, atol=TIGHT)
        assert np.all(np.abs(raw / np.asarray(dims) - 1) <= 0.12), (family, dims, raw)  # built from the dims
        for role, m in parts.items():
            assert _closed_outward(m), (family, spec.params.get("style"), role)
        assert sum(len(m.faces) for m in parts.values()) <= BUDGET[family], family


def test_prism_faces_face_outward_whatever_the_profile_order():
    for prof in ([(0, 0), (2, 0), (2.2, 0.5), (0.3, 1.0)], [(0.3, 1.0), (2.2, 0.5), (2, 0), (0, 0)]):
        assert _closed_outward(prism_y(prof, 0.4, -0.4))


def test_new_families_are_drawable_and_sized():
    for family in ("tram", "tricyclist", "barrow"):
        d = SIZES[family]
        x = np.array([dims for dims, _ in _draws(family, 200)])
        assert np.all(x >= np.asarray(d.lo)) and np.all(x <= np.asarray(d.hi))
        assert np.allclose(x.mean(axis=0), d.mean, rtol=0.06), family
    assert {s.params["style"] for _, s in _draws("tricyclist", 40)} == {"cargo", "rickshaw"}
    assert {s.params["style"] for _, s in _draws("barrow", 40)} == {"wheelbarrow", "cart"}


def test_same_seed_same_bytes():
    for family in PROCEDURAL_FAMILIES:
        a = draw_asset(np.random.default_rng(5), family)
        b = draw_asset(np.random.default_rng(5), family)
        assert a == b
        pa, _ = fit_to_dims(_builder(family)(a[0], dict(a[1].params)).meshes(), a[0])
        pb, _ = fit_to_dims(_builder(family)(b[0], dict(b[1].params)).meshes(), b[0])
        assert sorted(pa) == sorted(pb)
        for role in pa:
            assert pa[role].vertices.tobytes() == pb[role].vertices.tobytes() and pa[role].faces.tobytes() == pb[role].faces.tobytes()


def _builder(family):
    from omnigen.scenes.assets.build import AGENT_BUILDERS

    return AGENT_BUILDERS[family]


def test_car_styles_all_occur_and_follow_the_dims():
    styles = [s.params["style"] for _, s in _draws("car", 600)]
    assert set(styles) == set(CAR_STYLES)
    for dims, s in _draws("car", 200):
        if s.params["style"] in ("suv", "pickup"):
            assert dims[2] > 1.62
        else:
            assert dims[2] <= 1.62


def _vehicle_cases():
    for style in CAR_STYLES:
        yield "car", style
    for family in ("van", "truck", "bus", "tram"):
        yield family, None


@pytest.mark.parametrize("family,style", list(_vehicle_cases()))
def test_front_and_back_differ(family, style):
    rng = np.random.default_rng(3)
    dims = {"car": (4.5, 1.8, 1.7 if style in ("suv", "pickup") else 1.48)}.get(family) or tuple(SIZES[family].mean)
    params = draw_params(rng, family, dims)
    if style:
        params["style"] = style
    parts, _ = agent_parts(AssetSpec(family, params), dims)
    l, h = dims[0], dims[2]
    head, tail = parts["headlight"].vertices, parts["taillight"].vertices
    assert head[:, 0].min() > 0.35 * l and head[:, 0].max() > 0.45 * l  # white at the front,
    assert tail[:, 0].max() < 0.0 and tail[:, 0].min() < -0.45 * l  # red at the back (a car's stop lamp atop the rear window)
    if family != "tram":  # plates at both ends
        plates = np.vstack([parts[r].vertices for r in ("plate", "plate_yellow") if r in parts])
        assert plates[:, 0].max() > 0.45 * l and plates[:, 0].min() < -0.45 * l
    if family in ("car", "van"):
        body = parts["paint"].vertices
        nose = body[body[:, 0] > 0.45 * l][:, 2].max()
        tail_top = body[body[:, 0] < -0.45 * l][:, 2].max()
        assert nose < tail_top - 0.05 * h, (nose, tail_top)  # the bonnet slopes down to a low nose
    if family == "car":
        g = parts["glass"].vertices
        z0, z1 = g[:, 2].min(), g[:, 2].max()
        bottom, top = g[np.isclose(g[:, 2], z0)], g[np.isclose(g[:, 2], z1)]
        front_run = bottom[:, 0].max() - top[:, 0].max()
        rear_run = top[:, 0].min() - bottom[:, 0].min()
        assert front_run > rear_run > -1e-9, (style, front_run, rear_run)  # a raked windscreen, an upright(er) rear
        v = np.vstack([m.vertices for m in parts.values()])
        widest = v[np.abs(v[:, 1]) > dims[1] / 2 - 0.04]  # only the mirrors stand out this far
        assert len(widest) and np.all(widest[:, 0] > 0.0)  # by the windscreen, in the front half


def test_cone_styles():
    draws = _draws("traffic_cone", 200)
    assert {s.params["style"] for _, s in draws} == set(CONE_STYLES)
    for dims, s in draws:
        if s.params["style"] == "barrel":
            assert 0.5 < dims[0] < 0.7 and 0.9 < dims[2] < 1.1
        if s.params["style"] == "delineator":
            assert dims[0] == pytest.approx(0.4) and dims[2] >= 1.0
    dims, spec = draw_asset(np.random.default_rng(0), "traffic_cone", "barrel")
    assert spec.params["style"] == "barrel"


FURNITURE = [
    ("tree", (3.2, 3.0, 6.0), {"species": "round", "trunk_height": 2.8}),
    ("tree", (2.5, 2.5, 9.0), {"species": "conical", "trunk_height": 1.0}),
    ("tree", (1.6, 1.6, 10.0), {"species": "columnar"}),
    ("tree", (7.0, 7.0, 9.0), {"species": "spreading", "trunk_height": 3.0}),
    ("hedge", (12.0, 0.8, 1.2), {}),
    ("hedge", (6.0, 0.9, 1.0), {"clipped": False}),
    ("bush", (1.2, 1.0, 0.9), {}),
    ("planter", (1.5, 0.8, 1.3), {}),
    ("planter", (1.0, 1.0, 1.4), {"shape": "round", "material": "wood"}),
    ("signpost", (0.12, 0.7, 2.6), {}),
    ("signpost", (0.12, 0.8, 2.6), {"shape": "triangle"}),
    ("signpost", (0.12, 0.6, 2.6), {"shape": "square", "color": "blue"}),
    ("signpost", (0.12, 0.9, 2.8), {"shape": "rect", "color": "yellow"}),
    ("bus_shelter", (4.5, 1.6, 2.6), {}),
    ("fence", (10.0, 0.08, 1.1), {}),
    ("fence", (10.0, 0.08, 1.1), {"style": "picket"}),
    ("fence", (5.0, 0.1, 1.8), {"style": "panel"}),
    ("guardrail", (20.0, 0.3, 0.75), {}),
    ("bollard", (0.22, 0.22, 0.9), {"style": "dome"}),
]


@pytest.mark.parametrize("kind,dims,params", FURNITURE)
def test_furniture_kinds_fill_their_cuboid(kind, dims, params):
    raw_parts = props.FURNITURE_BUILDERS[kind](dims, params).meshes()
    _, raw = fit_to_dims(raw_parts, dims)
    assert np.allclose(raw, dims, rtol=0.01), (kind, raw)  # designed to the dims, not stretched
    parts = furniture_parts(kind, dims, params)
    lo, hi = bounds_of(parts)
    assert np.allclose(hi - lo, dims, atol=TIGHT) and np.allclose((hi + lo) / 2, 0.0, atol=TIGHT)
    for role, m in raw_parts.items():
        assert _closed_outward(m), (kind, params, role)
    assert sum(len(m.faces) for m in parts.values()) <= 1000


def test_unknown_furniture_kind_is_a_clear_error():
    with pytest.raises(ValueError, match="no furniture builder"):
        furniture_parts("spaceship", (1.0, 1.0, 1.0), {})


def test_every_role_has_a_material():
    """A role the materials rules do not know would stop both backends (KeyError) mid-render."""
    from omnigen.scenes.generate import SceneGenerator
    from omnigen.scenes.materials import agent_material, furniture_material

    scene = SceneGenerator("tiny", 6).frame(6, 0)
    for family in PROCEDURAL_FAMILIES:
        for dims, spec in _draws(family, 8):
            agent = Agent(1, family, (0.0, 0.0, 0.0), dims, 0.0, "moving", spec)
            for role in agent_parts(spec, dims)[0]:
                agent_material(role, agent, scene.lighting)
    for kind, dims, params in FURNITURE:
        item = Furniture("f", kind, (0.0, 0.0, 0.0), dims, 0.0, params, ())
        for role in furniture_parts(kind, dims, params):
            furniture_material(role, item, scene.weather, scene.lighting)
