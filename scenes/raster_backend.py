"""The raster backend: the fast preview. RenderObjects rasterised offscreen on EGL (scenes/gl_raster.py).

Headless GL: PyOpenGL is pointed at EGL (PYOPENGL_PLATFORM=egl unless already set) and Mesa's
software EGL (Debian: libegl1, libegl-mesa0, libgl1-mesa-dri; llvmpipe, no GPU needed) draws,
with pyrender's EGL context and pyrender's shading (see gl_raster.py for why not its renderer).

What a frame costs is kept small on two CPU cores by drawing few, large vertex buffers: the static
city is built into one buffer once per process (restyled per frame through a material table, not
rebuilt), and the frame's agents into another, built only for the agents whose cuboid reaches the
camera's view (nothing outside the view can change a pixel: no shadows, no reflections here).
What it is not: no shadows, no global illumination, no volumes. What it adds so previews still
look like the weather (all documented approximations):
- fog and haze: c = c_surface T + c_fog (1 - T), T = exp(-density d) with d the ray length,
  in linear colour, per fragment in the colour pass; the sky is at 2 km;
- the sky: a vertical gradient by ray elevation, tinted by time of day and cloud cover, drawn
  where no geometry is;
- rain and snow: screen-space streaks and flakes over the image, from the frame's own generator.

Pixel convention: pyrender's IntrinsicsCamera measures the principal point from the image's
corner, so it is given cx + 0.5, cy + 0.5 (conventions.md, "Measured facts about the renderers").
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402

from scenes.description import Scene  # noqa: E402
from scenes.gl_raster import ZFAR, ZNEAR, GLRaster, projection, view_matrix  # noqa: E402
from scenes.meshes import agent_object, compile_scene, static_materials, static_objects, world_box  # noqa: E402
from scenes.seeding import frame_streams  # noqa: E402

SKY_DISTANCE = 2000.0
CULL_MARGIN = 0.25  # metres added to an agent's bounding sphere when testing it against the view


@dataclass
class RasterFrame:
    rgb: np.ndarray  # (H, W, 3) uint8, sRGB
    depth: np.ndarray  # (H, W) float32, camera z in metres; inf where nothing was hit
    instance: np.ndarray  # (H, W) uint16, 0 background, k = instance id


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


def _soup(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles as a flat-shaded soup: (positions, per-face normals), float32, 3 vertices a face.

    Flat shading needs vertices split per face; soups of many parts and objects concatenate into
    one vertex buffer, so this runs once over all of them.
    """
    tri = vertices[faces]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(length > 0, n / np.where(length > 0, length, 1.0), 0.0)
    return tri.reshape(-1, 3).astype(np.float32), np.repeat(n, 3, axis=0).astype(np.float32)


def visible_agents(agents, K: np.ndarray, R: np.ndarray, t: np.ndarray, width: int, height: int) -> list[int]:
    """Indices of the agents whose bounding sphere (plus CULL_MARGIN) reaches the view frustum.

    Conservative: every agent that can colour a pixel is kept (its mesh lies inside its cuboid).
    """
    if not agents:
        return []
    c = np.array([a.center for a in agents], dtype=np.float64) @ R.T + t.reshape(3)
    r = np.linalg.norm(np.array([a.dims for a in agents], dtype=np.float64), axis=1) / 2.0 + CULL_MARGIN
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    planes = np.array([[fx, 0.0, cx + 0.5], [-fx, 0.0, width - 0.5 - cx], [0.0, fy, cy + 0.5], [0.0, -fy, height - 0.5 - cy]])
    planes /= np.linalg.norm(planes, axis=1, keepdims=True)
    inside = (c @ planes.T >= -r[:, None]).all(axis=1) & (c[:, 2] + r >= ZNEAR) & (c[:, 2] - r <= ZFAR)
    return np.nonzero(inside)[0].tolist()


def unoccluded_agents(agents, chosen: list[int], K: np.ndarray, R: np.ndarray, t: np.ndarray, static_z: np.ndarray) -> list[int]:
    """Those of `chosen` not wholly hidden by the static city (camera z `static_z`, inf for sky).

    An agent's mesh lies inside its cuboid, so it can only cover pixels whose centres lie in the
    box of the cuboid's projected corners, no nearer than the cuboid's nearest corner. If the city
    is nearer than that (less a depth-precision margin) at every such pixel, no pixel shows the
    agent and it is skipped. Agents reaching behind the near plane are always kept.
    """
    if not chosen:
        return []
    H, W = static_z.shape
    l_, w_, h_ = (np.array([agents[k].dims[i] for k in chosen]) / 2.0 for i in range(3))
    sx = np.array([-1, 1, 1, -1, -1, 1, 1, -1], dtype=np.float64)
    sy = np.array([-1, -1, 1, 1, -1, -1, 1, 1], dtype=np.float64)
    sz = np.array([-1, -1, -1, -1, 1, 1, 1, 1], dtype=np.float64)
    yaw = np.array([agents[k].yaw for k in chosen])
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    local_x, local_y = l_[:, None] * sx, w_[:, None] * sy
    centre = np.array([agents[k].center for k in chosen], dtype=np.float64)
    world = np.stack([centre[:, 0:1] + c * local_x - s * local_y, centre[:, 1:2] + s * local_x + c * local_y,
                      centre[:, 2:3] + h_[:, None] * sz], axis=-1)  # (N, 8, 3)
    cam = world @ R.T + t.reshape(3)
    z = cam[..., 2]
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
        verts, faces, face_slots, n_verts = [], [], [], 0
        for obj in self._statics:
            rot, shift = obj.matrix_world[:3, :3], obj.matrix_world[:3, 3]
            for mesh in obj.parts.values():
                verts.append(np.asarray(mesh.vertices, dtype=np.float64) @ rot.T + shift)
                faces.append(np.asarray(mesh.faces) + n_verts)
                face_slots.append(np.full(len(mesh.faces), len(face_slots), dtype=np.float32))
                n_verts += len(mesh.vertices)
        pos, nrm = _soup(np.concatenate(verts), np.concatenate(faces))
        self._n_static_slots = len(face_slots)
        self.gl.static.upload(pos, nrm, np.repeat(np.concatenate(face_slots), 3), None)
        self._static_table = self._static_materials(scene)
        self._agents_key: tuple | None = None
        self._ranges: dict[int, tuple[int, int]] = {}

    def _static_materials(self, scene: Scene) -> np.ndarray:
        return material_table([m for obj in self._statics for m in static_materials(scene, obj).values()])

    def update(self, scene: Scene) -> None:
        """Next frame: new agents, new weather and lighting, same city."""
        if scene.city is not self.scene.city and scene.city != self.scene.city:
            raise ValueError("RasterScene.update needs the same city; build a new RasterScene for another")
        if scene.weather != self.scene.weather or scene.lighting != self.scene.lighting:
            self._static_table = self._static_materials(scene)
        self.scene = scene
        self._agents_key = None

    # -- agents -------------------------------------------------------------------------------

    def _prepare_agents(self, K, R, t, width: int, height: int, static_z: np.ndarray | None = None) -> None:
        """The agent buffer for this camera: the agents in view, in scene order, and the material table.

        With `static_z` (the static city's camera z), agents wholly behind it are left out too.
        """
        key = (id(self.scene), K.tobytes(), R.tobytes(), t.tobytes(), width, height)
        if key == self._agents_key:
            return
        agents = self.scene.agents
        chosen = visible_agents(agents, K, R, t, width, height)
        if static_z is not None:
            chosen = unoccluded_agents(agents, chosen, K, R, t, static_z)
        verts, faces, face_slots, face_ids, materials = [], [], [], [], []
        self._ranges = {}
        n_verts = n_faces = 0
        for k in chosen:
            obj = agent_object(agents[k], self.scene)
            rot, shift = obj.matrix_world[:3, :3], obj.matrix_world[:3, 3]
            begin = n_faces
            for role, mesh in obj.parts.items():
                verts.append(np.asarray(mesh.vertices) @ rot.T + shift)
                faces.append(np.asarray(mesh.faces) + n_verts)
                face_slots.append(np.full(len(mesh.faces), self._n_static_slots + len(materials), dtype=np.float32))
                materials.append(obj.materials[role])
                n_verts += len(mesh.vertices)
                n_faces += len(mesh.faces)
            face_ids.append(np.full(n_faces - begin, obj.instance_id, dtype=np.float32))
            self._ranges[obj.instance_id] = (3 * begin, 3 * (n_faces - begin))
        if faces:
            pos, nrm = _soup(np.concatenate(verts), np.concatenate(faces))
            slots, ids = np.repeat(np.concatenate(face_slots), 3), np.repeat(np.concatenate(face_ids), 3)
        else:
            pos = nrm = np.zeros((0, 3))
            slots = ids = np.zeros(0)
        self.gl.make_current()
        self.gl.agents.upload(pos, nrm, slots, ids)
        table = np.concatenate([self._static_table, material_table(materials)])
        self.gl.set_materials(table)
        self._agents_key = key

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

    def _camera(self, K, R, t, width: int, height: int, prepare: bool = True):
        K, R, t = (np.asarray(a, dtype=np.float64) for a in (K, R, t))
        t = t.reshape(3)
        self.gl.make_current()
        if prepare:
            self._prepare_agents(K, R, t, width, height)
        return K, R, t, projection(K, width, height) @ view_matrix(R, t)

    def render(self, K: np.ndarray, R: np.ndarray, t: np.ndarray, width: int, height: int, effects: bool = True) -> RasterFrame:
        """Render with an OpenCV camera: X_cam = R X_world + t, pixels as in the contract."""
        K, R, t, VP = self._camera(K, R, t, width, height, prepare=False)
        depth, instance = self._id_pass(K, R, t, VP, width, height)
        light_dir, radiance, ambient = self._light()
        rgb = self.gl.color_pass(VP, -R.T @ t, light_dir, radiance, ambient, width, height,
                                 self._atmosphere(K, R, width, height) if effects else None)
        rgb = np.ascontiguousarray(rgb)
        weather = self.scene.weather
        if effects and weather.precipitation > 0 and weather.kind in ("rain", "snow"):
            rgb = _precipitation(rgb, self.scene)
        return RasterFrame(rgb, depth, instance)

    def labels(self, K: np.ndarray, R: np.ndarray, t: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """(depth, instance) of the id pass alone, no colour: labels for another renderer's image
        of the same geometry (the Cycles backend's)."""
        K, R, t, VP = self._camera(K, R, t, width, height, prepare=False)
        return self._id_pass(K, R, t, VP, width, height)

    def _id_pass(self, K, R, t, VP, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Masks and depth from the id pass, drawn without multisampling: ids are exact (never
        averaged at edges) and each pixel's depth belongs to the object its id names (the colour
        pass keeps its antialiasing). The static city is drawn first, so agents wholly behind it
        are not even built."""
        static_z = self.gl.id_static(VP, width, height)
        self._prepare_agents(K, R, t, width, height, static_z)
        instance, depth = self.gl.id_agents(VP, width, height)
        return depth, instance

    def render_instances(self, K: np.ndarray, R: np.ndarray, t: np.ndarray, width: int, height: int,
                         instance_ids: list[int]) -> np.ndarray:
        """The instance image of only the agents in `instance_ids`, nothing else drawn (uint16).

        Used for silhouettes "drawn alone": when the given agents' projections do not overlap, each
        one's pixels here are exactly its full silhouette (rigs/annotate.py).
        """
        K, R, t, VP = self._camera(K, R, t, width, height)
        ranges = [self._ranges[int(i)] for i in sorted({int(i) for i in instance_ids}) if int(i) in self._ranges]
        first = np.array([r[0] for r in ranges], dtype=np.int32)
        count = np.array([r[1] for r in ranges], dtype=np.int32)
        return self.gl.ids_of_ranges(VP, width, height, first, count)

    def _light(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(direction the sunlight travels, sun radiance, ambient) of the current scene."""
        scene = self.scene
        light = scene.lighting
        d = np.asarray(light.sun_direction, dtype=np.float64)
        n = np.linalg.norm(d)
        direction = -d / n if n > 0 else np.array([0.0, 0.0, -1.0])
        sun = max(light.sun_strength, 0.0) * (1.0 if light.sun_elevation > 0 else 0.0)
        radiance = np.asarray(_sun_color(light.sun_elevation)) * 1.2 * sun
        amb = 0.05 + 0.45 * light.sky_strength
        if light.street_lights_on and light.sky_strength < 0.3:
            amb += 0.08  # street lighting, approximated as ambient in the preview
        return direction, radiance, np.array(_sky_colors(scene)[1]) * amb * 1.6

    def _atmosphere(self, K: np.ndarray, R: np.ndarray, width: int, height: int) -> dict:
        """What the colour pass needs for fog, haze and sky (gl_raster.GLRaster.color_pass).

        The model (module doc): c = c_surface T + c_fog (1 - T), T = exp(-density d), d the ray
        length, in linear colour; the sky, at SKY_DISTANCE, a gradient by the ray's elevation.
        """
        zenith, horizon = _sky_colors(self.scene)
        # NDC (x, y) -> pixel (u, v) = ((x + 1) W / 2 - 0.5, (1 - y) H / 2 - 0.5) -> camera ray
        # ((u - cx) / fx, (v - cy) / fy, 1) -> world ray R^T ray.
        A = np.array([[width / (2 * K[0, 0]), 0.0, (width / 2 - 0.5 - K[0, 2]) / K[0, 0]],
                      [0.0, -height / (2 * K[1, 1]), (height / 2 - 0.5 - K[1, 2]) / K[1, 1]],
                      [0.0, 0.0, 1.0]])
        return {"fog_density": float(self.scene.weather.fog_density), "fog_color": np.asarray(horizon) * 0.9,
                "zenith": zenith, "horizon": horizon, "sky_distance": SKY_DISTANCE, "ndc_to_world": R.T @ A}

    def close(self) -> None:
        self.gl.close()


def _sun_color(elevation: float) -> list[float]:
    warm = float(np.clip(1.0 - elevation / 20.0, 0.0, 1.0))  # low sun is orange
    return [1.0, 1.0 - 0.25 * warm, 1.0 - 0.55 * warm]


def _sky_colors(scene: Scene) -> tuple[tuple[float, float, float], tuple[float, float, float]]:
    """(zenith, horizon) linear colours for the preview sky and fog."""
    light, w = scene.lighting, scene.weather
    s = light.sky_strength
    clear_z, clear_h = np.array([0.12, 0.25, 0.6]), np.array([0.55, 0.65, 0.8])
    grey = np.array([0.45, 0.47, 0.5])
    k = float(w.cloud_cover)
    z = clear_z * (1 - k) + grey * k
    h = clear_h * (1 - k) + grey * 1.1 * k
    if -6 < light.sun_elevation < 10:  # dawn and dusk: a warm horizon
        warm = 1 - abs(light.sun_elevation - 2) / 8
        h = h * (1 - 0.5 * warm) + np.array([0.9, 0.45, 0.2]) * 0.5 * warm
    z, h = z * s, h * s
    if w.kind == "fog":
        h = np.maximum(h, grey * s)
    return tuple(np.clip(z, 0.003, 1).tolist()), tuple(np.clip(h, 0.005, 1).tolist())


def _precipitation(rgb: np.ndarray, scene: Scene) -> np.ndarray:
    """Rain streaks or snow flakes over the image, from the frame's own generator."""
    from PIL import Image, ImageDraw

    rng = frame_streams(scene.dataset_seed, scene.frame_index)["extra"]
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
