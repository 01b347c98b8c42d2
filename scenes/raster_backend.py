"""The raster backend: the fast preview. RenderObjects rasterised offscreen on EGL (scenes/gl_raster.py).

Headless GL: PyOpenGL is pointed at EGL (PYOPENGL_PLATFORM=egl unless already set) and Mesa's
software EGL (Debian: libegl1, libegl-mesa0, libgl1-mesa-dri; llvmpipe, no GPU needed) draws,
with pyrender's EGL context and pyrender's shading (see gl_raster.py for why not its renderer).

What a frame costs is kept small on two CPU cores by drawing few, large vertex buffers: the static
city is built into one indexed buffer once per process (restyled per frame through a material
table, not rebuilt; parts whose bounds miss the view, or the sun's map, are not drawn), and the
frame's agents into another, built only for the agents whose cuboid reaches the camera's view.
What it is not: no global illumination, no volumes, no reflections but the sky's. What it draws so
previews look like the world (issue 26; all documented approximations, docs/scenes.md):
- procedural surfaces by role (materials.Surface), from world position alone (gl_raster.py);
- sun shadows: a depth map from the sun over what the camera sees (view_ground,
  shadow_projection); none when the sun gives under MIN_SUN_SHARE of the daylight;
- light (illumination): sun, sky and ground light, the camera's exposure, and at night the
  street lamps nearest the view; the sky's light on a surface scales with the sky it sees
  (sky_view_map: a street between towers sees a third of it, a roof all of it), and the camera
  meters the light where it looks (metered_sky_view) and then, as an automatic exposure, opens up
  (at most AE_MAX_GAIN) for a frame whose mean is under 18% grey (gl_raster.auto_exposure);
- contact shadows: a soft dark quad under each agent (contact_quads), colour only;
- fog and haze: c = c_surface T + c_fog (1 - T), T = exp(-density d) with d the ray length,
  in linear colour, per fragment in the colour pass; the sky is at 2 km;
- the sky: a vertical gradient by ray elevation, tinted by time of day and cloud cover, drawn
  where no geometry is;
- rain and snow: screen-space streaks and flakes over the image, from the frame's own generator.
Agents outside the view cast no shadow into it (they are not built): a car just outside the frame
loses the shadow it would throw inside it.

Pixel convention: pyrender's IntrinsicsCamera measures the principal point from the image's
corner, so it is given cx + 0.5, cy + 0.5 (conventions.md, "Measured facts about the renderers").
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Callable
from dataclasses import dataclass, replace

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402

from omnigen.scenes.description import Scene  # noqa: E402
from omnigen.camera import Camera  # noqa: E402
from omnigen.geometry import cuboid_corners, rots_z  # noqa: E402
from omnigen.scenes.gl_raster import MAX_LAMPS, SHADOW_SIZE, ZFAR, ZNEAR, GLRaster, Light  # noqa: E402
from omnigen.scenes.materials import PATTERNS, agent_surface, building_surface, furniture_surface, ground_surface  # noqa: E402
from omnigen.scenes.meshes import (compile_scene, frame_agent, frame_statics, lamp_lights, static_objects,  # noqa: E402
                           world_box)
from omnigen.scenes.road_wear import road_wear_map  # noqa: E402
from omnigen.scenes.seeding import instant_extra_rng  # noqa: E402

SKY_DISTANCE = 2000.0
SKY_ZENITH, SKY_HORIZON = (0.15, 9.0 / 7.0), (0.6, 3.0 / 7.0)  # (clear: of the daylight, overcast: of the sky's light) (_sky_colors)
CULL_MARGIN = 0.25  # metres added to an agent's bounding sphere when testing it against the view
SHADOW_REACH = 160.0  # metres along a view ray that the sun's shadow map covers (beyond: unshadowed)
SUN_SCALE = 0.9  # Lighting.sun_strength (Blender W/m^2) -> the shader's sun radiance
EXPOSURE_KEY = 1.3  # the camera exposes a white horizontal surface in the frame's daylight to this
MAX_EXPOSURE = 5.0
CLEAR_SKY_LIGHT = 0.10  # a cloudless sky's light on a white horizontal face, in the sun's units (illumination)
AE_MAX_GAIN = 4.0  # the camera's automatic exposure opens up at most 2 stops past the daylight exposure (gl_raster.auto_exposure)
HORIZON_KEY = 2.2  # the exposure's cap: the horizon's sky reads at most this (white, as photographs show it; dusk's colours kept)  # at night the camera's gain stops here
LAMP_INTENSITY = 16.0
GROUND_ALBEDO = 0.15  # what a street's ground (asphalt, paving, kerbs) returns of the light reaching it (illumination)
CONTACT_SHADOW = 0.7  # the darkening at the middle of the ground under an agent (gl_raster._DECAL_FS)
MIN_SKY_VIEW = 0.3  # the least share of the sky a street canyon's floor sees (street_canyon)
SVF_CELL, SVF_REACH, SVF_DIRECTIONS = 2.0, 120.0, 16  # the sky-view map: cell (m), how far it looks (m), azimuths
MIN_SUN_SHARE = 0.25  # below this share of the daylight the sun casts no visible shadow: no shadow pass
DRAW_ORDER = {"road": 1, "sidewalk": 1, "lawn": 1, "marking_white": 2, "marking_yellow": 2, "ground": 3}  # others 0
NON_CASTERS = frozenset({"window", "window_lit", "frame", "shopfront", "marking_white", "marking_yellow"})  # lie on other faces: cast no shadow


@dataclass
class RasterFrame:
    rgb: np.ndarray | None  # (H, W, 3) uint8, sRGB; None until `finish` is called (render(defer=True))
    depth: np.ndarray  # (H, W) float32, camera z in metres; inf where nothing was hit
    instance: np.ndarray  # (H, W) uint16, 0 background, k = instance id
    finish: Callable[[], np.ndarray] | None = None  # render(defer=True): the colour image (shading it if need be)
    shade: Callable[[], None] | None = None  # render(defer=True): hand the colour pass to the rasteriser now


def material_table(materials) -> np.ndarray:
    """Materials as the shader's table, (S, 8) float32: base rgb, metallic, emission rgb, roughness.

    Emission as pyrender drew it (its emissive factor is applied twice, so the previous backend
    passed a square root): clip(emission_color * min(strength / 10, 1), 0, 1).
    """
    rows = [(*m.base_color, m.metallic, *m.emission_color, min(m.emission_strength / 10.0, 1.0), m.roughness) for m in materials]
    if not rows:
        return np.zeros((0, 8), dtype=np.float32)
    r = np.array(rows, dtype=np.float64)
    out = np.empty((len(r), 8), dtype=np.float32)
    out[:, :4] = r[:, :4]
    out[:, 4:7] = np.clip(r[:, 4:7] * r[:, 7:8], 0.0, 1.0)
    out[:, 7] = np.maximum(r[:, 8], 0.04)
    return out


def surface_rows(surfaces, vertices_per_part) -> np.ndarray:
    """Each vertex's surface pattern row (materials.Surface.row), (vertices, 4) float32: a part's
    surface repeated over its vertices."""
    if not surfaces:
        return np.zeros((0, 4), dtype=np.float32)
    rows = np.array([sf.row() for sf in surfaces], dtype=np.float32).reshape(-1, 4)
    return np.repeat(rows, np.asarray(vertices_per_part, dtype=np.int64), axis=0)


def visible_agents(agents, camera: Camera) -> list[int]:
    """Indices of the agents whose bounding sphere (plus CULL_MARGIN) reaches the view frustum.

    Conservative: every agent that can colour a pixel is kept (its mesh lies inside its cuboid).
    """
    if not agents:
        return []
    K, width, height = camera.K, camera.width, camera.height
    c = camera.to_camera(np.array([a.center for a in agents], dtype=np.float64))
    r = np.linalg.norm(np.array([a.dims for a in agents], dtype=np.float64), axis=1) / 2.0 + CULL_MARGIN
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    planes = np.array([[fx, 0.0, cx + 0.5], [-fx, 0.0, width - 0.5 - cx], [0.0, fy, cy + 0.5], [0.0, -fy, height - 0.5 - cy]])
    planes /= np.linalg.norm(planes, axis=1, keepdims=True)
    inside = (c @ planes.T >= -r[:, None]).all(axis=1) & (c[:, 2] + r >= ZNEAR) & (c[:, 2] - r <= ZFAR)
    return np.nonzero(inside)[0].tolist()


def unoccluded_agents(agents, chosen: list[int], camera: Camera, static_z: np.ndarray) -> list[int]:
    """Those of `chosen` not wholly hidden by the static city (camera z `static_z`, inf for sky).

    An agent's mesh lies inside its cuboid, so it can only cover pixels whose centres lie in the
    box of the cuboid's projected corners, no nearer than the cuboid's nearest corner. If the city
    is nearer than that (less a depth-precision margin) at every such pixel, no pixel shows the
    agent and it is skipped. Agents reaching behind the near plane are always kept.
    """
    if not chosen:
        return []
    H, W = static_z.shape
    centre = np.array([agents[k].center for k in chosen], dtype=np.float64)
    dims = np.array([agents[k].dims for k in chosen], dtype=np.float64)
    world = cuboid_corners(centre, dims, rots_z([agents[k].yaw for k in chosen]))  # (N, 8, 3)
    cam = camera.to_camera(world)
    z = cam[..., 2]
    K = camera.K
    keep = []
    for i, k in enumerate(chosen):
        zmin = float(z[i].min())
        if zmin <= ZNEAR * 2:
            keep.append(k)
            continue
        u = K[0, 0] * cam[i, :, 0] / z[i] + K[0, 2]
        v = K[1, 1] * cam[i, :, 1] / z[i] + K[1, 2]
        i0, i1 = max(int(math.floor(u.min())), 0), min(int(math.ceil(u.max())), W - 1)
        j0, j1 = max(int(math.floor(v.min())), 0), min(int(math.ceil(v.max())), H - 1)
        if i0 > i1 or j0 > j1:
            keep.append(k)  # nothing to test against (the frustum test kept it): keep, to be safe
            continue
        if not float(static_z[j0:j1 + 1, i0:i1 + 1].max()) < zmin - (0.05 + 0.002 * zmin):
            keep.append(k)
    return keep


class RasterScene:
    """A GL scene kept in step with a Scene; `update` swaps agents and restyles the rest.

    The static city's triangles are uploaded once (one vertex buffer, a material slot per part);
    per frame only the material table changes. Agents are built when a camera asks for them, for
    the agents in view only, into one vertex buffer carrying material slots and instance ids, so a
    colour pass is two draw calls, the id/depth pass two, and a silhouette pass one.
    """

    def __init__(self, scene: Scene) -> None:
        self.scene = scene
        self.gl = GLRaster()
        self._statics = static_objects(scene.city)
        # One vertex range a part (an object's role); slots stay in _static_materials' order
        # whatever the order in the buffer. Parts lying on other faces (windows, frames, road
        # markings: 40% of downtown's triangles) cast no shadow: the sun's depth pass leaves them out.
        buildings = {b.building_id: b for b in scene.city.buildings}
        parts = []  # (casts a shadow, slot, world vertices, faces, surface, role)
        for obj in self._statics:
            rot, shift = obj.matrix_world[:3, :3], obj.matrix_world[:3, 3]
            for role, mesh in obj.parts.items():
                parts.append((role not in NON_CASTERS, len(parts), np.asarray(mesh.vertices, dtype=np.float64) @ rot.T + shift,
                              np.asarray(mesh.faces), static_surface(scene.city, buildings, obj, role), role))
        self._n_static_slots = len(parts)
        # Drawn nearest-first, roughly: buildings and furniture, then the street surfaces, the
        # ground under everything last, so the depth test rejects hidden fragments before the
        # (costly) surface shading runs on them. Stable: scene order within each group.
        parts.sort(key=lambda q: DRAW_ORDER.get(q[5], 0))
        verts, faces, n_verts = [], [], 0
        for _, _, v, f, _, _ in parts:
            verts.append(v)
            faces.append(f + n_verts)
            n_verts += len(v)
        slots = np.concatenate([np.full(len(q[2]), q[1], dtype=np.float32) for q in parts])
        self.gl.static.upload(np.concatenate(verts), np.concatenate(faces), slots, None,
                              surface_rows([q[4] for q in parts], [len(q[2]) for q in parts]))
        # Each part's index range and world bounds: what a camera or the sun's map cannot reach is
        # not drawn (conservative: a part is skipped only when its whole box is outside).
        counts = np.array([3 * len(q[3]) for q in parts], dtype=np.int64)
        self._part_first = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        self._part_count = counts
        self._part_lo = np.array([q[2].min(axis=0) if len(q[2]) else np.zeros(3) for q in parts])
        self._part_hi = np.array([q[2].max(axis=0) if len(q[2]) else np.zeros(3) for q in parts])
        self._part_casts = np.array([q[0] for q in parts], dtype=bool)
        self._part_kind = np.array([PATTERNS[q[4].pattern] for q in parts], dtype=np.int64)
        self._all_parts = np.ones(len(parts), dtype=bool)
        lo, hi = self._part_lo, self._part_hi
        self._part_corners = np.stack([np.stack([np.where(i & 1, hi[:, 0], lo[:, 0]), np.where(i & 2, hi[:, 1], lo[:, 1]),
                                                 np.where(i & 4, hi[:, 2], lo[:, 2])], axis=-1) for i in range(8)], axis=1)
        self._static_table = self._static_materials(scene)
        self._agents_key: tuple | None = None
        self._ranges: dict[int, tuple[int, int]] = {}
        self._top = max((p.top_z + p.roof_height for b in scene.city.buildings for p in b.parts), default=10.0)
        self._canyon = street_canyon(scene.city)
        self._svf, self._svf_xform = sky_view_map(scene.city)
        self.gl.set_sky_view(self._svf)
        wear, self._wear_xform = road_wear_map(scene.city)
        self.gl.set_road_wear(wear)
        lamps = lamp_lights(replace(scene, lighting=replace(scene.lighting, street_lights_on=True)))
        self._lamps = np.array([lamp.position for lamp in lamps], dtype=np.float64).reshape(-1, 3)

    def _static_materials(self, scene: Scene) -> np.ndarray:
        return material_table([m for obj in frame_statics(scene) for m in obj.materials.values()])

    def update(self, scene: Scene) -> None:
        """Next frame: new agents, new weather and lighting, same city."""
        if scene.city is not self.scene.city and scene.city != self.scene.city:
            raise ValueError("RasterScene.update needs the same city; build a new RasterScene for another")
        if scene.weather != self.scene.weather or scene.lighting != self.scene.lighting:
            self._static_table = self._static_materials(scene)
        self.scene = scene
        self._agents_key = None

    # -- agents -------------------------------------------------------------------------------

    def _prepare_agents(self, camera: Camera, static_z: np.ndarray | None = None) -> None:
        """The agent buffer for this camera: the agents in view, in scene order, and the material table.

        With `static_z` (the static city's camera z), agents wholly behind it are left out too.
        """
        key = (id(self.scene), camera.K.tobytes(), camera.R.tobytes(), camera.t.tobytes(), camera.width, camera.height)
        if key == self._agents_key:
            return
        agents = self.scene.agents
        chosen = visible_agents(agents, camera)
        if static_z is not None:
            chosen = unoccluded_agents(agents, chosen, camera, static_z)
        verts, faces, vert_slots, vert_ids, materials, surfaces, part_verts = [], [], [], [], [], [], []
        self._ranges = {}
        n_verts = n_faces = 0
        for k in chosen:
            obj = frame_agent(self.scene, k)
            rot, shift = obj.matrix_world[:3, :3], obj.matrix_world[:3, 3]
            begin, first_vert = n_faces, n_verts
            for role, mesh in obj.parts.items():
                verts.append(np.asarray(mesh.vertices) @ rot.T + shift)
                faces.append(np.asarray(mesh.faces) + n_verts)
                vert_slots.append(np.full(len(mesh.vertices), self._n_static_slots + len(materials), dtype=np.float32))
                materials.append(obj.materials[role])
                surfaces.append(agent_surface(role))
                part_verts.append(len(mesh.vertices))
                n_verts += len(mesh.vertices)
                n_faces += len(mesh.faces)
            vert_ids.append(np.full(n_verts - first_vert, obj.instance_id, dtype=np.float32))
            self._ranges[obj.instance_id] = (3 * begin, 3 * (n_faces - begin))
        if faces:
            pos, tri = np.concatenate(verts), np.concatenate(faces)
            slots, ids = np.concatenate(vert_slots), np.concatenate(vert_ids)
        else:
            pos, tri = np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint32)
            slots = ids = np.zeros(0)
        self.gl.make_current()
        self.gl.agents.upload(pos, tri, slots, ids, surface_rows(surfaces, part_verts))
        self.gl.set_decals(*contact_quads([agents[k] for k in chosen]))
        table = np.concatenate([self._static_table, material_table(materials)])
        self.gl.set_materials(table)
        self._agents_key = key

    def _static_ranges(self, M: np.ndarray, keep: np.ndarray, near: bool, kinds: bool = False):
        """Vertex ranges (first, count) of the static parts in `keep` whose bounding box reaches
        the clip volume of the 4x4 `M` (world -> clip): a part is left out only when all eight
        corners of its box lie outside one of the volume's side planes (or, with `near`, all
        behind the camera's near plane), so no part that can touch a pixel is ever left out."""
        corners = self._part_corners
        c = corners @ M[:3, :3].T + M[:3, 3]  # (P, 8, 3) clip x, y, z
        w = corners @ M[3, :3] + M[3, 3]  # (P, 8)
        out = ((c[..., 0] < -w).all(axis=1) | (c[..., 0] > w).all(axis=1) | (c[..., 1] < -w).all(axis=1)
               | (c[..., 1] > w).all(axis=1))
        if near:
            out |= (c[..., 2] < -w).all(axis=1)
        idx = np.nonzero(keep & ~out & (self._part_count > 0))[0]
        ranges = (self._part_first[idx].astype(np.int32), self._part_count[idx].astype(np.int32))
        return (ranges, self._part_kind[idx]) if kinds else ranges

    # -- inspection -------------------------------------------------------------------------

    def objects_summary(self) -> list[dict]:
        """Name, instance id, class and world box of every object (from the geometry drawn)."""
        out = []
        for obj in compile_scene(self.scene):
            center, dims, yaw = world_box(obj)
            out.append({"name": obj.name, "instance_id": obj.instance_id, "category": obj.category,
                        "center": center.tolist(), "dims": dims.tolist(), "yaw": yaw})
        return out

    # -- rendering --------------------------------------------------------------------------

    def _view_projection(self, camera: Camera, prepare: bool = True) -> np.ndarray:
        """The camera's world -> clip matrix (VP), with the GL context current."""
        self.gl.make_current()
        if prepare:
            self._prepare_agents(camera)
        VP = camera.gl_projection(ZNEAR, ZFAR) @ camera.gl_view()
        if not prepare:  # render and labels draw the static city (silhouettes, prepare=True, do not)
            self.gl.static_view, self.gl.static_view_kinds = self._static_ranges(VP, self._all_parts, near=True, kinds=True)
        return VP

    def render(self, camera: Camera, effects: bool = True, defer: bool = False) -> RasterFrame:
        """Render with an OpenCV camera: X_cam = R X_world + t, pixels as in the contract.

        defer: return once the masks and depth are read, with no colour drawn yet: the frame's
        `shade()` hands the colour pass to the rasteriser's threads (after annotation, whose
        silhouette passes would otherwise wait for it; a camera annotation rejects is never
        shaded) and `finish()` gives the image (shading first if need be). Call finish() before
        the next render or update; work done between the two overlaps the shading."""
        VP = self._view_projection(camera, prepare=False)
        depth, instance = self._id_pass(camera, VP)
        width, height = camera.width, camera.height
        light = self._light(camera)
        atmosphere = self._atmosphere(camera) if effects else None
        scene, view = self.scene, (self.gl.static_view, self.gl.static_view_kinds, self.gl.static_shadow)
        read: Callable[[], np.ndarray] | None = None

        def shade() -> None:
            nonlocal read
            if read is None:
                self.gl.make_current()
                self.gl.static_view, self.gl.static_view_kinds, self.gl.static_shadow = view
                read = self.gl.color_draw(VP, camera.center, light, width, height, atmosphere)

        def finish() -> np.ndarray:
            shade()
            rgb = np.ascontiguousarray(read())
            weather = scene.weather
            if effects and weather.precipitation > 0 and weather.kind in ("rain", "snow"):
                rgb = _precipitation(rgb, scene)
            return rgb

        if defer:
            return RasterFrame(None, depth, instance, finish, shade)
        return RasterFrame(finish(), depth, instance)

    def labels(self, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        """(depth, instance) of the id pass alone, no colour: labels for another renderer's image
        of the same geometry (the Cycles backend's)."""
        return self._id_pass(camera, self._view_projection(camera, prepare=False))

    def _id_pass(self, camera: Camera, VP: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Masks and depth from the id pass, drawn without multisampling: ids are exact (never
        averaged at edges) and each pixel's depth belongs to the object its id names (the colour
        pass keeps its antialiasing). The static city is drawn first, so agents wholly behind it
        are not even built."""
        static_z = self.gl.id_static(VP, camera.width, camera.height)
        self._prepare_agents(camera, static_z)
        instance, depth = self.gl.id_agents(VP, camera.width, camera.height)
        return depth, instance

    def render_instances(self, camera: Camera, instance_ids: list[int]) -> np.ndarray:
        """The instance image of only the agents in `instance_ids`, nothing else drawn (uint16).

        Used for silhouettes "drawn alone": when the given agents' projections do not overlap, each
        one's pixels here are exactly its full silhouette (rigs/annotate.py).
        """
        VP = self._view_projection(camera)
        ranges = [self._ranges[int(i)] for i in sorted({int(i) for i in instance_ids}) if int(i) in self._ranges]
        first = np.array([r[0] for r in ranges], dtype=np.int32)
        count = np.array([r[1] for r in ranges], dtype=np.int32)
        return self.gl.ids_of_ranges(VP, camera.width, camera.height, first, count)

    def _light(self, camera: Camera) -> Light:
        """The frame's light for this camera: illumination(scene), the sun's shadow map over the
        view and the street lamps nearest to it."""
        ground = view_ground(camera)
        light = illumination(self.scene, metered_sky_view(self._canyon, self._svf, self._svf_xform, ground))
        light.canyon, light.svf_xform, light.wear_xform = self._canyon, self._svf_xform, self._wear_xform
        if light.sun_share >= MIN_SUN_SHARE:
            lvp, texel = shadow_projection(ground, light.direction, self.scene.city.bounds, self._top)
            light.shadow_lvp, light.normal_bias = lvp, 1.5 * texel
            self.gl.static_shadow = self._static_ranges(lvp, self._part_casts, near=False)
        if self.scene.lighting.street_lights_on and self._lamps is not None and len(self._lamps):
            focus = ground[1:].mean(axis=0)
            near = np.argsort(np.linalg.norm(self._lamps - focus, axis=1), kind="stable")[:MAX_LAMPS]
            light.lamps = np.column_stack([self._lamps[near], np.full(len(near), LAMP_INTENSITY)])
        return light

    def _atmosphere(self, camera: Camera) -> dict:
        """What the colour pass needs for fog, haze and sky (gl_raster.GLRaster.color_pass).

        The model (module doc): c = c_surface T + c_fog (1 - T), T = exp(-density d), d the ray
        length, in linear colour; the sky, at SKY_DISTANCE, a gradient by the ray's elevation.
        """
        K, R, width, height = camera.K, camera.R, camera.width, camera.height
        zenith, horizon = _sky_colors(self.scene)
        # NDC (x, y) -> pixel (u, v) = ((x + 1) W / 2 - 0.5, (1 - y) H / 2 - 0.5) -> camera ray
        # ((u - cx) / fx, (v - cy) / fy, 1) -> world ray R^T ray.
        A = np.array([[width / (2 * K[0, 0]), 0.0, (width / 2 - 0.5 - K[0, 2]) / K[0, 0]],
                      [0.0, -height / (2 * K[1, 1]), (height / 2 - 0.5 - K[1, 2]) / K[1, 1]],
                      [0.0, 0.0, 1.0]])
        h = np.asarray(horizon)
        fog = 0.5 * h + 0.5 * _luminance(h)  # haze scatters nearly white: half the horizon's tint
        return {"fog_density": float(self.scene.weather.fog_density), "fog_color": fog,
                "zenith": zenith, "horizon": horizon, "sky_distance": SKY_DISTANCE, "ndc_to_world": R.T @ A}

    def close(self) -> None:
        self.gl.close()


def static_surface(city, buildings: dict, obj, role: str):
    """The procedural surface of a static part (materials.py decides; see materials.Surface)."""
    if obj.kind in ("ground", "markings"):
        return ground_surface(role, city)
    if obj.kind == "building":
        return building_surface(role, buildings[obj.name])
    return furniture_surface(role)


def _smoothstep(a: float, b: float, x: float) -> float:
    """GLSL's smoothstep (the shader's sky_view ramp, on the CPU)."""
    u = min(max((x - a) / (b - a), 0.0), 1.0)
    return u * u * (3.0 - 2.0 * u)


def _luminance(c) -> float:
    return float(np.dot(np.asarray(c, dtype=np.float64), (0.2126, 0.7152, 0.0722)))


def illumination(scene: Scene, sky_view: float = 1.0) -> Light:
    """Sun, sky and ground light and the camera's exposure for a frame's weather and hour.

    Units: a white horizontal face receives E = E_sun + E_sky. The sun's radiance follows
    Lighting.sun_strength (already dimmed by cloud and by a low sun); the sky gives a clear day
    about a tenth of its daylight (CLEAR_SKY_LIGHT: a cloudless sky's diffuse share of the
    daylight is 10-15% with the sun above 30 degrees), more under scattered cloud and an overcast
    day most of it (diffuse: soft, no hard shadows), tinted like the sky; the ground returns
    GROUND_ALBEDO of what falls on it to faces looking down or sideways, scaled by `sky_view`: the
    floor of a street canyon receives the sky's light by its sky view and the sun on a similar
    share of it (shade is the rest), so it returns less than open ground (a tower's foot is not
    lit from below as a car park is). The exposure is a camera's: a white horizontal face in the
    frame's daylight reads EXPOSURE_KEY, but the horizon is not blown out (dusk), and at night the
    gain stops at MAX_EXPOSURE, so the night stays dark except under lamps and lit windows.
    `sky_view` is the share of the sky that the camera's surroundings see (street_canyon; 1: open
    ground): a camera down in a street canyon meters the light down there, as an automatic exposure
    does, so the open sky and the sunlit tops above it come out brighter than the street.
    """
    light, w = scene.lighting, scene.weather
    zenith, horizon = (np.asarray(c) for c in _sky_colors(scene))
    d = np.asarray(light.sun_direction, dtype=np.float64)
    n = np.linalg.norm(d)
    direction = -d / n if n > 0 else np.array([0.0, 0.0, -1.0])
    radiance = _sun_radiance(light)
    e_sun, e_sky = daylight(scene)
    tint = 0.5 * (zenith + horizon)
    tint = 0.3 * tint / max(_luminance(tint), 1e-6) + 0.7
    sky_ambient = tint * e_sky
    # the ground's light on faces looking down or sideways: its albedo times what reaches it; a
    # canyon's floor sees the sky, and on about as large a share of it the sun, by its sky view
    ground_ambient = np.array([1.0, 0.95, 0.88]) * GROUND_ALBEDO * (e_sun + e_sky) * sky_view
    exposure = min(EXPOSURE_KEY / max(e_sun + e_sky * sky_view, 1e-6), HORIZON_KEY / max(_luminance(horizon), 1e-6), MAX_EXPOSURE)
    return Light(direction=tuple(direction), radiance=tuple(radiance), sky_ambient=tuple(sky_ambient),
                 ground_ambient=tuple(ground_ambient), zenith=tuple(zenith), horizon=tuple(horizon),
                 exposure=float(max(exposure, 0.2)), shadow_radius=1.0 + 8.0 * float(w.cloud_cover),
                 sun_share=e_sun / max(e_sun + e_sky, 1e-9), snow_cover=float(w.snow_cover),
                 contact_shadow=CONTACT_SHADOW, sky_wall=sky_on_walls(light.sun_elevation, float(w.cloud_cover)),
                 aureole=aureole_share(light.sun_elevation, float(w.cloud_cover)), max_gain=float(min(AE_MAX_GAIN, MAX_EXPOSURE / max(exposure, 0.2))))


CIE_OVERCAST_WALL = 0.397  # the CIE overcast sky's light on a wall, of its light on a roof (sky_on_walls)
AUREOLE_DEGREES = 15.0  # the clear sky's bright ring round the sun that a caster of the sun's shadow hides too (aureole_share)


def aureole_share(sun_elevation: float, cloud_cover: float) -> float:
    """The share of the sky's light on a roof that comes from within AUREOLE_DEGREES of the sun:
    0.14-0.15 for the CIE clear sky with the sun above 25 degrees, none under an overcast one
    (cloud cover mixes, as for sky_on_walls) or with the sun down.

    Why: a clear sky is brightest round the sun, and what hides the sun from a point hides that
    ring with it (solar engineering's circumsolar light, shaded with the beam). The shader gives a
    face that sees the sun the ring's light where its shadow lookup says the sun is visible, and
    the rest of the sky by its sky view (gl_raster: sky light in the colour shader), so shade is
    that much deeper than an evenly bright sky makes it.
    """
    if sun_elevation <= 0.0:
        return 0.0
    return (1.0 - float(np.clip(cloud_cover, 0.0, 1.0))) * _cie_clear_sky(int(round(min(sun_elevation, 89.0))))[3]


@functools.lru_cache(maxsize=128)
def _cie_clear_sky(elevation: int) -> tuple[float, float, float, float]:
    """The CIE standard clear sky's (ISO 15469 type 12) light on a wall facing the sun's azimuth,
    at right angles to it and away from it, of its light on a roof, and the share of a roof's that
    comes from within AUREOLE_DEGREES of the sun, the sun `elevation` degrees up: numerical
    integrals over the sky (the sun's disc itself is the direct light, not here)."""
    zen = np.linspace(0.0, math.pi / 2, 91)[:-1] + math.pi / 360
    az = np.linspace(0.0, 2.0 * math.pi, 181)[:-1]
    Z, A = np.meshgrid(zen, az, indexing="ij")
    d = np.stack([np.sin(Z) * np.cos(A), np.sin(Z) * np.sin(A), np.cos(Z)], axis=-1)
    zs = math.radians(90.0 - max(float(elevation), 0.0))
    chi = np.arccos(np.clip(d @ np.array([math.sin(zs), 0.0, math.cos(zs)]), -1.0, 1.0))
    L = ((1.0 + 10.0 * (np.exp(-3.0 * chi) - math.exp(-1.5 * math.pi)) + 0.45 * np.cos(chi) ** 2)
         * (1.0 - np.exp(-0.32 / np.cos(Z))))
    w = L * np.sin(Z)  # solid angle (the grid's steps cancel in the ratios)
    roof = float((w * d[..., 2]).sum())
    walls = [float((w * np.clip(d @ np.array([math.cos(a), math.sin(a), 0.0]), 0.0, None)).sum()) / roof
             for a in (0.0, math.pi / 2, math.pi)]
    aureole = float((w * d[..., 2])[chi < math.radians(AUREOLE_DEGREES)].sum()) / roof
    return walls[0], walls[1], walls[2], aureole


def sky_on_walls(sun_elevation: float, cloud_cover: float) -> tuple[float, float, float]:
    """A wall's share of the sky's light on a roof, as (a, b, c): a + b cos(phi) + c cos^2(phi)
    with phi the wall's azimuth from the sun's (the shader's sky_wall; tilted faces blend it with a
    roof's, gl_raster w_sky).

    An evenly bright sky gives every wall 0.5. A real sky does not: the CIE overcast sky (zenith
    three times the horizon) gives a wall CIE_OVERCAST_WALL, and a clear sky's light comes mostly
    from around the sun (the CIE clear sky: a wall facing away from a sun 35 degrees up gets 0.38,
    one facing it 1.15), so a wall in its own shade is darker than an even sky would make it.
    Cloud cover mixes the two, as _sky_colors mixes the skies. No sun above the horizon: the
    overcast figure (twilight's sky has no bright region to face).
    """
    k = float(np.clip(cloud_cover, 0.0, 1.0))
    if sun_elevation <= 0.0:
        return (CIE_OVERCAST_WALL, 0.0, 0.0)
    toward, side, away, _ = _cie_clear_sky(int(round(min(sun_elevation, 89.0))))
    a, b, c = side, 0.5 * (toward - away), 0.5 * (toward + away) - side
    return ((1 - k) * a + k * CIE_OVERCAST_WALL, (1 - k) * b, (1 - k) * c)


def _sun_radiance(light) -> np.ndarray:
    """The sun's radiance (linear rgb): Lighting.sun_strength, warm when low, none below the horizon."""
    sun = max(light.sun_strength, 0.0) * (1.0 if light.sun_elevation > 0 else 0.0)
    return np.asarray(_sun_color(light.sun_elevation)) * SUN_SCALE * sun


def daylight(scene: Scene) -> tuple[float, float]:
    """(E_sun, E_sky): the sun's and the open sky's light on a white horizontal face (luminance,
    illumination's units). A cloudless sky gives CLEAR_SKY_LIGHT of the sky's strength, an overcast
    one 0.6 (most of the daylight then)."""
    light, w = scene.lighting, scene.weather
    e_sun = _luminance(_sun_radiance(light)) * max(math.sin(math.radians(light.sun_elevation)), 0.0) / math.pi
    return e_sun, light.sky_strength * (CLEAR_SKY_LIGHT + (0.6 - CLEAR_SKY_LIGHT) * w.cloud_cover)


def street_canyon(city) -> tuple[float, float, float]:
    """The city's typical street canyon, (H, svf, W): the median building height H (m), the sky
    view factor at the middle of its floor, svf = cos(atan(2 H / W)) (Oke's infinite canyon), and
    W (m) between the facades: the median road width plus two median sidewalks.

    Why: at the bottom of a downtown canyon the buildings hide most of the sky (H/W 1.7: a third
    of it). The shader takes H and W: mirrors (windows, car paint) show the facades opposite
    below their roofline, and a wall's sky view rises from the street's (sky_view_map) to the
    whole sky at H (gl_raster sky_view); svf (kept at least MIN_SKY_VIEW: gaps, crossings and
    setbacks let sky in) is the typical floor's figure, for reports. No buildings: (0, 1, 1).
    """
    heights = [max(p.top_z for p in b.parts) for b in city.buildings if b.parts]
    if not heights or not city.roads:
        return (0.0, 1.0, 1.0)
    h = float(np.median(heights))
    walks = [s.width for s in city.sidewalks if s.kind == "sidewalk"]
    w = float(np.median([r.width for r in city.roads])) + 2.0 * (float(np.median(walks)) if walks else 0.0)
    svf = math.cos(math.atan(2.0 * h / max(w, 1.0)))
    return (h, float(max(svf, MIN_SKY_VIEW)), w)


def sky_view_map(city, cell: float = SVF_CELL, reach: float = SVF_REACH, directions: int = SVF_DIRECTIONS
                 ) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """The sky view factor of the city's ground and roofs on a square grid, and where it lies.

    Each cell's height is the top of the building standing on it (0: street); its sky view is what
    an upward-facing surface there sees of an evenly bright sky, mean over `directions` azimuths of
    cos^2 of the horizon's elevation (the highest building top within `reach`, seen from the
    cell's own height). A street between tall buildings sees a third of the sky, a crossing or a
    plaza more, a roof above its neighbours all of it: the sky's light on them scales with it
    (gl_raster sky_view). The grid has an open margin (outside it: its edge). Returns (ny, nx)
    float32 and (x0, y0, 1 / side, cell) for Light.svf_xform.
    """
    xmin, ymin, xmax, ymax = city.bounds
    margin = 2.0 * cell
    side = max(xmax - xmin, ymax - ymin) + 2.0 * margin
    n = int(math.ceil(side / cell))
    side = n * cell
    x0, y0 = xmin - margin, ymin - margin
    centres = x0 + (np.arange(n) + 0.5) * cell
    X, Y = np.meshgrid(centres, y0 + (np.arange(n) + 0.5) * cell)  # row j: y
    height = np.zeros((n, n), dtype=np.float64)
    for b in city.buildings:
        for part in b.parts:
            poly = np.asarray(part.footprint, dtype=np.float64)
            if len(poly) < 3:
                continue
            i0, i1 = np.clip(((poly[:, 0].min() - x0) / cell, (poly[:, 0].max() - x0) / cell + 1), 0, n).astype(int)
            j0, j1 = np.clip(((poly[:, 1].min() - y0) / cell, (poly[:, 1].max() - y0) / cell + 1), 0, n).astype(int)
            px, py = X[j0:j1, i0:i1], Y[j0:j1, i0:i1]
            inside = np.zeros(px.shape, dtype=bool)
            for (ax, ay), (bx, by) in zip(poly, np.roll(poly, -1, axis=0)):  # even-odd rule
                crosses = (ay > py) != (by > py)
                with np.errstate(divide="ignore", invalid="ignore"):
                    xc = ax + (py - ay) * (bx - ax) / (by - ay)
                inside ^= crosses & (px < xc)
            top = part.top_z + 0.5 * part.roof_height
            height[j0:j1, i0:i1] = np.where(inside, np.maximum(height[j0:j1, i0:i1], top), height[j0:j1, i0:i1])
    jj, ii = np.mgrid[0:n, 0:n]
    steps = np.arange(1, int(reach / cell) + 1, dtype=np.float64)
    cos2 = np.zeros((n, n), dtype=np.float64)
    for k in range(directions):
        a = 2.0 * math.pi * k / directions
        tan = np.zeros((n, n), dtype=np.float64)
        for s in steps:
            j = np.clip(np.rint(jj + s * math.sin(a)).astype(np.int64), 0, n - 1)
            i = np.clip(np.rint(ii + s * math.cos(a)).astype(np.int64), 0, n - 1)
            np.maximum(tan, (height[j, i] - height) / (s * cell), out=tan)
        cos2 += 1.0 / (1.0 + tan * tan)
    return (cos2 / directions).astype(np.float32), (float(x0), float(y0), float(1.0 / side), float(cell))


def metered_sky_view(canyon: tuple[float, float, float], svf: np.ndarray, xform, ground: np.ndarray) -> float:
    """The share of the sky seen where the camera meters: the mean of the sky view (gl_raster
    sky_view, a wall's ramp) at the camera and at the nine points its view reaches (view_ground),
    as a camera's average metering weighs the street below and the tops and sky above alike."""
    x0, y0, inv_side, cell = xform
    n = svf.shape[0]
    i = np.clip(((ground[:, 0] - x0) / cell).astype(np.int64), 0, n - 1)
    j = np.clip(((ground[:, 1] - y0) / cell).astype(np.int64), 0, n - 1)
    g = svf[j, i].astype(np.float64)
    ramp = np.array([_smoothstep(0.0, max(canyon[0], 1e-3), float(z)) for z in ground[:, 2]])
    return float(np.mean(g + (1.0 - g) * ramp))


def view_ground(camera: Camera) -> np.ndarray:
    """The camera centre and where rays through the image's corners, edge midpoints and centre
    meet the ground (z = 0), or SHADOW_REACH along them when sooner: (10, 3), what the view spans."""
    K, R, width, height = camera.K, camera.R, camera.width, camera.height
    cam = camera.center
    u = np.array([-0.5, width / 2, width - 0.5])
    v = np.array([-0.5, height / 2, height - 0.5])
    uu, vv = np.meshgrid(u, v)
    pix = np.stack([uu.ravel(), vv.ravel(), np.ones(9)])
    rays = (R.T @ np.linalg.solve(K, pix)).T
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    reach = np.full(9, SHADOW_REACH)
    down = rays[:, 2] < -1e-9
    reach[down] = np.minimum(reach[down], -cam[2] / rays[down, 2])
    return np.vstack([cam, cam + rays * np.maximum(reach, 0.0)[:, None]])


def shadow_projection(points: np.ndarray, direction, bounds, top: float) -> tuple[np.ndarray, float]:
    """The sun's orthographic view-projection over `points` (what the camera sees), and its texel (m).

    Across the sunlight it spans the points (plus 3 m); along it, the whole city from the ground
    to its highest roof, so every caster between the sun and a seen point is in the map.
    """
    f = np.asarray(direction, dtype=np.float64)
    f = f / np.linalg.norm(f)
    up = np.array([0.0, 0.0, 1.0]) if abs(f[2]) < 0.99 else np.array([1.0, 0.0, 0.0])
    right = np.cross(f, up)
    right /= np.linalg.norm(right)
    L = np.stack([right, np.cross(right, f), f])
    p = points @ L.T
    lo, hi = p[:, :2].min(axis=0) - 3.0, p[:, :2].max(axis=0) + 3.0
    xmin, ymin, xmax, ymax = bounds
    corners = np.array([[x, y, z] for x in (xmin - 5, xmax + 5) for y in (ymin - 5, ymax + 5) for z in (-1.0, top + 2.0)])
    depth = corners @ f
    d0, d1 = float(depth.min()), float(depth.max())
    O = np.eye(4)
    O[0, 0], O[0, 3] = 2.0 / (hi[0] - lo[0]), -(hi[0] + lo[0]) / (hi[0] - lo[0])
    O[1, 1], O[1, 3] = 2.0 / (hi[1] - lo[1]), -(hi[1] + lo[1]) / (hi[1] - lo[1])
    O[2, 2], O[2, 3] = 2.0 / (d1 - d0), -(d1 + d0) / (d1 - d0)
    V = np.eye(4)
    V[:3, :3] = L
    return O @ V, float(max(hi - lo)) / SHADOW_SIZE


def contact_quads(agents) -> tuple[np.ndarray, np.ndarray]:
    """The contact-shadow quads under `agents` as triangles: (6 N, 3) world positions, 3 cm above
    the cuboid's base, and (6 N, 2) quad coordinates. A quad is the footprint grown by a quarter of
    its shorter side (at most 0.3 m), so the shadow fades out just beyond the agent."""
    if not agents:
        return np.zeros((0, 3)), np.zeros((0, 2))
    c = np.array([a.center for a in agents], dtype=np.float64)
    d = np.array([a.dims for a in agents], dtype=np.float64)
    yaw = np.array([a.yaw for a in agents], dtype=np.float64)
    margin = np.minimum(0.3, 0.25 * np.minimum(d[:, 0], d[:, 1]))
    hl, hw = d[:, 0] / 2 + margin, d[:, 1] / 2 + margin
    corner_uv = np.array([[-1, -1], [1, -1], [1, 1], [-1, -1], [1, 1], [-1, 1]], dtype=np.float64)  # two triangles
    lx, ly = corner_uv[None, :, 0] * hl[:, None], corner_uv[None, :, 1] * hw[:, None]
    cs, sn = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    z = (c[:, 2] - d[:, 2] / 2 + 0.03)[:, None]
    pos = np.stack([c[:, 0:1] + cs * lx - sn * ly, c[:, 1:2] + sn * lx + cs * ly, np.broadcast_to(z, lx.shape)], axis=-1)
    # quad coordinates: the footprint ends 0.6-0.9 of the way out (the shader fades from 0.7)
    uv = np.broadcast_to(corner_uv, (len(agents), 6, 2))
    return pos.reshape(-1, 3), uv.reshape(-1, 2)


def _sun_color(elevation: float) -> list[float]:
    warm = float(np.clip(1.0 - elevation / 20.0, 0.0, 1.0))  # low sun is orange
    return [1.0, 1.0 - 0.25 * warm, 1.0 - 0.55 * warm]


def _sky_colors(scene: Scene) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """(zenith, horizon) linear colours for the preview sky and fog."""
    light, w = scene.lighting, scene.weather
    s = light.sky_strength
    # a clear sky is near white low over the horizon (a long path through the air scatters every
    # colour) and deeper blue at the zenith
    clear_z, clear_h = np.array([0.08, 0.19, 0.55]), np.array([0.68, 0.74, 0.84])
    grey = np.array([0.45, 0.47, 0.5])
    k = float(w.cloud_cover)
    z = clear_z * (1 - k) + grey * k
    h = clear_h * (1 - k) + grey * 1.1 * k
    if -6 < light.sun_elevation < 10:  # dawn and dusk: a warm horizon
        warm = 1 - abs(light.sun_elevation - 2) / 8
        h = h * (1 - 0.5 * warm) + np.array([0.9, 0.45, 0.2]) * 0.5 * warm
    # luminances calibrated to the light on a white horizontal face, in illumination's units: a
    # clear sky's horizon reads SKY_HORIZON[0] of the daylight E = E_sun + E_sky (photographs show
    # it near white where sunlit asphalt, under a tenth of E, reads mid-grey: KITTI's clear skies
    # saturate), its zenith SKY_ZENITH[0]; with no sun
    # (twilight) at least 2.4 and 0.8 times the sky's own light. An overcast sky is the CIE
    # overcast sky, L = Lz (1 + 2 sin e) / 3 with E_sky / pi = 7/9 Lz: its zenith 9/7 of E_sky,
    # its horizon 3/7. Haze takes the horizon's radiance (_atmosphere).
    e_sun, e_sky = daylight(scene)
    zl = (1 - k) * max(SKY_ZENITH[0] * (e_sun + e_sky), 0.8 * e_sky) + k * SKY_ZENITH[1] * e_sky
    hl = (1 - k) * max(SKY_HORIZON[0] * (e_sun + e_sky), 2.4 * e_sky) + k * SKY_HORIZON[1] * e_sky
    z, h = z * (zl / _luminance(z)), h * (hl / _luminance(h))
    if w.kind == "fog":
        h = np.maximum(h, grey * s)
    return tuple(np.clip(z, 0.003, 1).tolist()), tuple(np.clip(h, 0.005, 1).tolist())


def _precipitation(rgb: np.ndarray, scene: Scene) -> np.ndarray:
    """Rain streaks or snow flakes over the image, from the frame's own generator."""
    from PIL import Image, ImageDraw

    rng = instant_extra_rng(scene.dataset_seed, scene.frame_index, scene.instant)  # frame_streams' "extra" at instant 0
    h, w = rgb.shape[:2]
    img = Image.fromarray(rgb)
    overlay = Image.new("RGBA", (w, h), (0, 0, 0, 0))
    draw = ImageDraw.Draw(overlay)
    density = scene.weather.precipitation
    scale = max(w, h) / 640.0
    if scene.weather.kind == "rain":
        n = int(600 * density * (w * h) / 640**2)
        slant = math.sin(scene.weather.wind_direction) * 0.3
        for _ in range(n):
            x, y = rng.uniform(0, w), rng.uniform(0, h)
            length = rng.uniform(8, 25) * scale
            draw.line([(x, y), (x + slant * length, y + length)], fill=(200, 205, 215, int(rng.uniform(40, 110))), width=1)
    else:
        n = int(900 * density * (w * h) / 640**2)
        for _ in range(n):
            x, y = rng.uniform(0, w), rng.uniform(0, h)
            r = rng.uniform(0.6, 2.2) * scale
            draw.ellipse([x - r, y - r, x + r, y + r], fill=(240, 240, 245, int(rng.uniform(120, 230))))
    img = Image.alpha_composite(img.convert("RGBA"), overlay)
    return np.asarray(img.convert("RGB"))
