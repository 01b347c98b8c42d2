"""The raster backend: the fast preview. RenderObjects drawn by pyrender, offscreen on EGL.

Headless GL: pyrender is pointed at EGL (PYOPENGL_PLATFORM=egl unless already set) and Mesa's
software EGL (Debian: libegl1, libegl-mesa0, libgl1-mesa-dri; llvmpipe, no GPU needed) draws.
What it is not: no shadows, no global illumination, no volumes. What it adds so previews still
look like the weather (all documented approximations, done on the image):
- fog and haze: a depth-based atmosphere, c = c_surface T + c_fog (1 - T), T = exp(-density d)
  with d the ray length (from the depth and K), computed in linear colour; the sky is at 2 km;
- the sky: a vertical gradient by ray elevation, tinted by time of day and cloud cover;
- rain and snow: screen-space streaks and flakes drawn from the frame's own generator.

Pixel convention: pyrender's IntrinsicsCamera measures the principal point from the image's
corner, so it is given cx + 0.5, cy + 0.5 (conventions.md, "Measured facts about the renderers").
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402
import pyrender  # noqa: E402

from scenes.description import Material, Scene  # noqa: E402
from scenes.meshes import RenderObject, compile_scene, world_box  # noqa: E402
from scenes.seeding import frame_streams  # noqa: E402

ZNEAR, ZFAR = 0.25, 3000.0
SKY_DISTANCE = 2000.0


@dataclass
class RasterFrame:
    rgb: np.ndarray  # (H, W, 3) uint8, sRGB
    depth: np.ndarray  # (H, W) float32, camera z in metres; inf where nothing was hit
    instance: np.ndarray  # (H, W) uint16, 0 background, k = instance id


def _pr_material(m: Material) -> pyrender.MetallicRoughnessMaterial:
    # pyrender multiplies the emissive factor in twice; pass its square root.
    strength = min(m.emission_strength / 10.0, 1.0)
    emissive = np.sqrt(np.clip(np.asarray(m.emission_color) * strength, 0.0, 1.0))
    return pyrender.MetallicRoughnessMaterial(
        baseColorFactor=[*m.base_color, 1.0], metallicFactor=float(m.metallic), roughnessFactor=float(max(m.roughness, 0.04)),
        emissiveFactor=emissive,
    )


def _set_material(pm: pyrender.MetallicRoughnessMaterial, m: Material) -> None:
    fresh = _pr_material(m)
    pm.baseColorFactor, pm.metallicFactor, pm.roughnessFactor = fresh.baseColorFactor, fresh.metallicFactor, fresh.roughnessFactor
    pm.emissiveFactor = fresh.emissiveFactor


def id_color(instance_id: int) -> tuple[int, int, int]:
    """The flat colour (0-255; pyrender divides by 255) of an instance in the segmentation pass:
    the 16-bit id in red (low byte) and green (high byte)."""
    return (instance_id & 255, (instance_id >> 8) & 255, 0)


def _material_key(m: Material) -> tuple:
    """What pyrender draws of a material: parts with equal keys can share one draw call."""
    return (tuple(m.base_color), float(m.metallic), float(m.roughness), tuple(m.emission_color), float(m.emission_strength))


def _triangles(mesh, matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A mesh as a flat-shaded triangle soup placed by `matrix`: (positions, per-face normals).

    Flat shading needs vertices split per face; the soup is in the frame `matrix` maps to, so
    parts of many objects can be concatenated into one draw call.
    """
    v = np.asarray(mesh.vertices, dtype=np.float64) @ matrix[:3, :3].T + matrix[:3, 3]
    tri = v[np.asarray(mesh.faces)]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(length > 0, n / np.where(length > 0, length, 1.0), 0.0)
    return tri.reshape(-1, 3).astype(np.float32), np.repeat(n, 3, axis=0).astype(np.float32)


def _merged_mesh(soups: list[tuple[np.ndarray, np.ndarray]], materials: list[Material], name: str,
                 origin: np.ndarray) -> tuple[pyrender.Mesh | None, list[pyrender.MetallicRoughnessMaterial]]:
    """One primitive per distinct material (first-appearance order, so the same frame always
    gives the same draw order), positions relative to `origin`. Why: pyrender's cost is per draw
    call, not per triangle, and a city has ~1,100 static parts but ~440 distinct materials."""
    groups: dict[tuple, list[int]] = {}
    for i, m in enumerate(materials):
        groups.setdefault(_material_key(m), []).append(i)
    prims, pms = [], []
    for idx in groups.values():
        pm = _pr_material(materials[idx[0]])
        pos = np.concatenate([soups[i][0] for i in idx]) - origin.astype(np.float32)
        nrm = np.concatenate([soups[i][1] for i in idx])
        prims.append(pyrender.Primitive(positions=pos, normals=nrm, material=pm))
        pms.append(pm)
    return (pyrender.Mesh(prims, name=name) if prims else None), pms


def _translation(origin: np.ndarray) -> np.ndarray:
    pose = np.eye(4)
    pose[:3, 3] = origin
    return pose


class RasterScene:
    """A pyrender scene kept in step with a Scene; `update` swaps agents and restyles the rest.

    Draw calls are what a frame costs (pyrender binds uniforms per primitive), so geometry is
    merged: the colour pass draws the static city as one node with one primitive per distinct
    material (kept between frames while the grouping is unchanged; only materials are restyled)
    and all agents as one node grouped the same way (rebuilt per frame). The segmentation pass
    needs per-agent ids, so it draws other nodes: the whole static city as one id-0 primitive and
    each agent as one primitive in its own frame. Segmentation-only nodes are hidden during the
    colour pass; colour-only nodes are simply left out of the segmentation map.
    """

    def __init__(self, scene: Scene) -> None:
        self.pr = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 0.0], ambient_light=[0.2, 0.2, 0.2])
        self.objects: dict[str, RenderObject] = {}
        self._renderer: pyrender.OffscreenRenderer | None = None
        self._sun: pyrender.Node | None = None
        self._static_soups: list[tuple[np.ndarray, np.ndarray]] = []
        self._static_roles: list[tuple[str, str]] = []
        self._static_color: pyrender.Node | None = None
        self._static_pms: list[pyrender.MetallicRoughnessMaterial] = []
        self._static_partition: tuple | None = None
        self._agent_color: pyrender.Node | None = None
        self._seg_nodes: dict[str, pyrender.Node] = {}
        self.scene = scene
        objs = compile_scene(scene)
        self._build_static([o for o in objs if o.kind != "agent"])
        self._restyle_static([o for o in objs if o.kind != "agent"])
        self._set_agents([o for o in objs if o.kind == "agent"])
        self._light(scene)

    # -- building ---------------------------------------------------------------------------

    def _build_static(self, statics: list[RenderObject]) -> None:
        """World-space soups of every static part (once per city) and the id-0 segmentation node."""
        for obj in statics:
            self.objects[obj.name] = obj
            for role, mesh in obj.parts.items():
                self._static_soups.append(_triangles(mesh, obj.matrix_world))
                self._static_roles.append((obj.name, role))
        pos = np.concatenate([s[0] for s in self._static_soups])
        seg = pyrender.Mesh([pyrender.Primitive(positions=pos, material=_pr_material(Material((0.0, 0.0, 0.0))))], name="static")
        self._seg_nodes["static"] = self.pr.add(seg, name="static_seg")

    def _restyle_static(self, statics: list[RenderObject]) -> None:
        """This frame's static materials: restyle in place, or regroup when equal materials changed."""
        by_name = {o.name: o for o in statics}
        for obj in statics:
            self.objects[obj.name] = obj
        materials = [by_name[name].materials[role] for name, role in self._static_roles]
        keys = [_material_key(m) for m in materials]
        first: dict[tuple, int] = {}
        partition = tuple(first.setdefault(k, len(first)) for k in keys)
        if partition == self._static_partition:
            reps = {}
            for i, g in enumerate(partition):
                reps.setdefault(g, materials[i])
            for g, pm in enumerate(self._static_pms):
                _set_material(pm, reps[g])
            return
        if self._static_color is not None:
            self.pr.remove_node(self._static_color)
        mesh, self._static_pms = _merged_mesh(self._static_soups, materials, "static", np.zeros(3))
        self._static_color = self.pr.add(mesh, name="static_color")
        self._static_partition = partition

    def _set_agents(self, agents: list[RenderObject]) -> None:
        """Replace the agents: one merged colour node, one segmentation node per agent."""
        for name in [n for n, o in self.objects.items() if o.kind == "agent"]:
            self.pr.remove_node(self._seg_nodes.pop(name))
            del self.objects[name]
        if self._agent_color is not None:
            self.pr.remove_node(self._agent_color)
            self._agent_color = None
        soups, materials = [], []
        for obj in agents:
            self.objects[obj.name] = obj
            local = [_triangles(mesh, np.eye(4)) for mesh in obj.parts.values()]
            seg = pyrender.Primitive(positions=np.concatenate([p for p, _ in local]), material=_pr_material(Material((0.0, 0.0, 0.0))))
            self._seg_nodes[obj.name] = self.pr.add(pyrender.Mesh([seg], name=obj.name), name=obj.name, pose=obj.matrix_world)
            for role, mesh in obj.parts.items():
                soups.append(_triangles(mesh, obj.matrix_world))
                materials.append(obj.materials[role])
        if soups:
            # A pose away from the origin keeps pyrender's distance sort of the two colour nodes
            # free of ties (ties fall back to set order, which differs between processes).
            origin = np.mean([o.matrix_world[:3, 3] for o in agents], axis=0) + np.array([0.0, 0.0, 0.5])
            mesh, _ = _merged_mesh(soups, materials, "agents", origin)
            self._agent_color = self.pr.add(mesh, name="agents_color", pose=_translation(origin))

    def _light(self, scene: Scene) -> None:
        light = scene.lighting
        if self._sun is not None:
            self.pr.remove_node(self._sun)
        d = np.asarray(light.sun_direction)
        # A directional light shines along its node's -z: point -z away from the sun.
        z = d / np.linalg.norm(d)
        x = np.cross([0.0, 0.0, 1.0], z)
        x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-6 else np.array([1.0, 0.0, 0.0])
        pose = np.eye(4)
        pose[:3, 0], pose[:3, 1], pose[:3, 2] = x, np.cross(z, x), z
        sun = max(light.sun_strength, 0.0) * (1.0 if light.sun_elevation > 0 else 0.0)
        self._sun = self.pr.add(pyrender.DirectionalLight(color=_sun_color(light.sun_elevation), intensity=1.2 * sun), pose=pose)
        amb = 0.05 + 0.45 * light.sky_strength
        if light.street_lights_on and light.sky_strength < 0.3:
            amb += 0.08  # street lighting, approximated as ambient in the preview
        self.pr.ambient_light = np.array(_sky_colors(scene)[1]) * amb * 1.6

    def update(self, scene: Scene) -> None:
        """Next frame: new agents, new weather and lighting, same city."""
        if scene.city is not self.scene.city and scene.city != self.scene.city:
            raise ValueError("RasterScene.update needs the same city; build a new RasterScene for another")
        objs = compile_scene(scene)
        self._restyle_static([o for o in objs if o.kind != "agent"])
        self._set_agents([o for o in objs if o.kind == "agent"])
        self.scene = scene
        self._light(scene)

    # -- inspection -------------------------------------------------------------------------

    def objects_summary(self) -> list[dict]:
        """Name, instance id, class and world box of every object (from the geometry drawn)."""
        out = []
        for name, obj in self.objects.items():
            center, dims, yaw = world_box(obj)
            out.append({"name": name, "instance_id": obj.instance_id, "category": obj.category,
                        "center": center.tolist(), "dims": dims.tolist(), "yaw": yaw})
        return out

    def _seg_map(self, wanted: set[int] | None = None) -> dict:
        """Segmentation colours of the segmentation nodes (all, or only the agents in `wanted`)."""
        out = {}
        for name, node in self._seg_nodes.items():
            iid = self.objects[name].instance_id if name in self.objects else 0
            if wanted is None or (iid in wanted and iid != 0):
                out[node] = id_color(iid)
        return out

    def _show_seg_nodes(self, visible: bool) -> None:
        for node in self._seg_nodes.values():
            node.mesh.is_visible = visible

    # -- rendering --------------------------------------------------------------------------

    def render(self, K: np.ndarray, R: np.ndarray, t: np.ndarray, width: int, height: int, effects: bool = True) -> RasterFrame:
        """Render with an OpenCV camera: X_cam = R X_world + t, pixels as in the contract."""
        K, R, t = (np.asarray(a, dtype=np.float64) for a in (K, R, t))
        cam = pyrender.IntrinsicsCamera(K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5, znear=ZNEAR, zfar=ZFAR)
        pose = np.eye(4)
        pose[:3, :3] = R.T @ np.diag([1.0, -1.0, -1.0])  # OpenCV -> OpenGL camera axes
        pose[:3, 3] = -R.T @ t.reshape(3)
        cam_node = self.pr.add(cam, pose=pose)
        try:
            r = self._get_renderer(width, height)
            self._show_seg_nodes(False)
            try:
                color, _ = r.render(self.pr)
            finally:
                self._show_seg_nodes(True)
            # Masks and depth come from the segmentation pass, which pyrender draws without
            # multisampling: ids are exact (never averaged at edges) and each pixel's depth
            # belongs to the object its id names. The colour pass keeps its antialiasing.
            seg, depth = r.render(self.pr, flags=pyrender.RenderFlags.SEG, seg_node_map=self._seg_map())
        finally:
            self.pr.remove_node(cam_node)
        seg = seg.astype(np.uint16)
        instance = (seg[..., 0] | (seg[..., 1] << 8)).astype(np.uint16)
        depth = depth.astype(np.float32)
        depth[depth <= 0] = np.inf
        rgb = color[..., :3].copy()
        if effects:
            rgb = self._atmosphere(rgb, depth, K, R, width, height)
        return RasterFrame(rgb, depth, instance)

    def render_instances(self, K: np.ndarray, R: np.ndarray, t: np.ndarray, width: int, height: int,
                         instance_ids: list[int]) -> np.ndarray:
        """The instance image of only the agents in `instance_ids`, nothing else drawn (uint16).

        Used for silhouettes "drawn alone": when the given agents' projections do not overlap, each
        one's pixels here are exactly its full silhouette (rigs/annotate.py).
        """
        K, R, t = (np.asarray(a, dtype=np.float64) for a in (K, R, t))
        cam = pyrender.IntrinsicsCamera(K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5, znear=ZNEAR, zfar=ZFAR)
        pose = np.eye(4)
        pose[:3, :3] = R.T @ np.diag([1.0, -1.0, -1.0])
        pose[:3, 3] = -R.T @ t.reshape(3)
        seg_map = self._seg_map({int(i) for i in instance_ids})
        cam_node = self.pr.add(cam, pose=pose)
        try:
            seg, _ = self._get_renderer(width, height).render(self.pr, flags=pyrender.RenderFlags.SEG, seg_node_map=seg_map)
        finally:
            self.pr.remove_node(cam_node)
        seg = seg.astype(np.uint16)
        return (seg[..., 0] | (seg[..., 1] << 8)).astype(np.uint16)

    def _get_renderer(self, width: int, height: int) -> pyrender.OffscreenRenderer:
        r = self._renderer
        if r is None or r.viewport_width != width or r.viewport_height != height:
            if r is not None:
                r.delete()
            r = self._renderer = pyrender.OffscreenRenderer(width, height)
        return r

    def _atmosphere(self, rgb: np.ndarray, depth: np.ndarray, K, R, width: int, height: int) -> np.ndarray:
        scene = self.scene
        u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
        rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)
        ray_len = np.linalg.norm(rays, axis=-1)
        world_dir = (rays / ray_len[..., None]) @ R  # R^T applied to each ray: camera -> world
        zenith, horizon = (np.asarray(c) for c in _sky_colors(scene))
        elev = np.clip(world_dir[..., 2], 0.0, 1.0)[..., None]
        sky = horizon * (1 - elev) ** 2 + zenith * (1 - (1 - elev) ** 2)
        lin = (rgb.astype(np.float64) / 255.0) ** 2.2
        hit = np.isfinite(depth)
        lin = np.where(hit[..., None], lin, sky)
        dist = np.where(hit, depth * ray_len, SKY_DISTANCE)
        trans = np.exp(-scene.weather.fog_density * dist)[..., None]
        fog_col = horizon * 0.9
        lin = lin * trans + fog_col * (1 - trans)
        out = (np.clip(lin, 0, 1) ** (1 / 2.2) * 255.0 + 0.5).astype(np.uint8)
        if scene.weather.precipitation > 0 and scene.weather.kind in ("rain", "snow"):
            out = _precipitation(out, scene)
        return out

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.delete()
            self._renderer = None


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
