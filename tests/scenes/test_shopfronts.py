"""A city centre at street level (issue 26): shopfronts on tall buildings' ground floors (glazing
across the frontage in a surround of its own, awnings over some shops that clear people on the
footway and reach into no neighbour), downtown's kerbs mostly taken by parked cars, and the road
wear read without llvmpipe's anisotropic filter (which took minutes on a dashcam frame)."""

from __future__ import annotations

import numpy as np
import pytest
from shapely.geometry import MultiPoint, Point, Polygon

from omnigen.scenes.assets.static import AWNING_CLEARANCE, AWNING_DEPTH, STALLRISER, building_parts, footprints
from omnigen.scenes.generate import SceneGenerator
from omnigen.scenes.layout import build_city
from omnigen.scenes.materials import building_material
from omnigen.scenes.preset import load_preset

pytestmark = pytest.mark.filterwarnings("ignore::DeprecationWarning")


@pytest.fixture(scope="module")
def downtown():
    city = build_city(load_preset("downtown"), 0)
    occ = footprints(city)
    return city, {b.building_id: building_parts(b, occ).meshes() for b in city.buildings}


def _tall(b) -> bool:
    return any(p.base_z < 1.0 and p.top_z - p.base_z > 12.0 for p in b.parts)


def test_tall_buildings_have_shopfronts_and_low_ones_none(downtown):
    city, parts = downtown
    tall = [b for b in city.buildings if _tall(b)]
    # (a tall building closed in by neighbours on every side has no frontage to put shops in)
    assert tall and np.mean(["shopfront" in parts[b.building_id] for b in tall]) > 0.8
    assert all("shopfront" not in parts[b.building_id] and "awning" not in parts[b.building_id]
               for b in city.buildings if not _tall(b))
    # some shops put out awnings, not every one
    with_awnings = sum("awning" in parts[b.building_id] for b in tall)
    assert 0.2 * len(tall) < with_awnings < len(tall)


def test_shop_glazing_fills_the_ground_floor_frontage(downtown):
    """The glass of a ground floor is most of its surround (a shop window between narrow piers),
    not a row of storey windows: at least 0.4 of its area, doors glazed to the floor."""
    city, parts = downtown
    for b in [b for b in city.buildings if _tall(b)][:10]:
        m = parts[b.building_id]
        z_top = b.parts[0].base_z + b.facade.floor_height
        glass = [m[r] for r in ("window", "window_lit") if r in m]
        area = lambda piece, sel: sum(  # noqa: E731
            0.5 * np.linalg.norm(np.cross(v[f[1]] - v[f[0]], v[f[2]] - v[f[0]]))
            for v in [piece.vertices] for f in piece.faces if sel(v[f].mean(axis=0)))
        ground = lambda c: c[2] < z_top - 0.05  # noqa: E731
        shop_glass = sum(area(g, ground) for g in glass)
        surround = area(m["shopfront"], lambda c: True)
        assert shop_glass > 0.4 * surround
        lowest = min(g.vertices[:, 2].min() for g in glass)
        assert lowest < b.parts[0].base_z + 0.1 < b.parts[0].base_z + STALLRISER  # a door glazed to the floor


def test_awnings_clear_people_and_reach_into_no_neighbour(downtown):
    city, parts = downtown
    others = {b.building_id: [Polygon(p.footprint) for p in b.parts] for b in city.buildings}
    seen = 0
    for b in city.buildings:
        if "awning" not in parts[b.building_id]:
            continue
        v = parts[b.building_id]["awning"].vertices
        ground = min(p.base_z for p in b.parts)
        assert v[:, 2].min() >= ground + AWNING_CLEARANCE - 1e-6  # the tallest pedestrian (1.95 m) walks under
        own = [Polygon(p.footprint) for p in b.parts]
        for k in range(0, len(v), 16):  # one awning: its sloping slab and its valance, 8 corners each
            hull = MultiPoint([tuple(x) for x in v[k:k + 16, :2]]).convex_hull
            assert min(hull.distance(o) for o in own) < 0.05  # it hangs from its own wall
            reach = max(min(o.exterior.distance(Point(x)) for o in own) for x in v[k:k + 16, :2])
            assert reach <= AWNING_DEPTH[1] + 0.1
            for other, polys in others.items():
                if other != b.building_id:
                    assert not any(hull.intersects(p) for p in polys)
        seen += 1
    assert seen > 0


def test_shopfront_surrounds_are_mostly_darker_than_the_walls_above(downtown):
    """Most shopfront surrounds are dark (painted timber and metal, dark stone): a real ground
    floor is much darker than the facade above in daylight."""
    city, _ = downtown
    scene = SceneGenerator("downtown", 0).frame(0, 0)
    tall = [b for b in city.buildings if _tall(b)]
    lum = lambda m: float(np.dot(m.base_color, (0.2126, 0.7152, 0.0722)))  # noqa: E731
    darker = [lum(building_material("shopfront", b, scene.weather, scene.lighting)) < 0.5 * lum(b.facade.wall) for b in tall]
    assert np.mean(darker) > 0.6


def test_downtown_kerbs_are_mostly_taken():
    """A city centre's kerbs by day: most spaces taken. Parked bodies cover over a fifth of the
    parking lanes' whole length (junction and crosswalk clearances and the gaps between cars
    included); the old 0.2-0.45 draw covered under a sixth in these frames."""
    gen = SceneGenerator("downtown", 0)
    for i in range(3):
        scene = gen.frame(0, i)
        lanes = [lane for road in scene.city.roads for lane in road.lanes if lane.kind == "parking"]
        parked = sum(a.dims[0] for a in scene.agents if a.state == "parked")
        assert parked > 0.2 * sum(lane.length for lane in lanes)


def test_road_wear_is_not_filtered_by_the_drivers_anisotropic_filter(noon_raster):
    """llvmpipe's anisotropic texture filter (Mesa 22.3) took 4 minutes for the asphalt of one
    640 x 640 dashcam frame; the shader filters the road-wear map along the footprint itself, so
    the texture must keep the filter off (1: isotropic)."""
    from OpenGL import GL as gl

    _, _, rs = noon_raster
    rs.gl.make_current()
    gl.glBindTexture(gl.GL_TEXTURE_2D, rs.gl._wear_tex)
    value = float(gl.glGetTexParameterfv(gl.GL_TEXTURE_2D, 0x84FE))  # GL_TEXTURE_MAX_ANISOTROPY
    gl.glBindTexture(gl.GL_TEXTURE_2D, 0)
    assert value == 1.0
