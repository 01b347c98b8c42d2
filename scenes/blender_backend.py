"""The Blender backend: RenderObjects as a bpy scene. The only module in omnigen importing bpy.

What it builds, and why this way:
- Meshes from numpy with foreach_set (no bpy.ops), flat-shaded, one object per RenderObject,
  named as in the description; agents carry pass_index = instance id (Cycles' IndexOB pass) and
  custom properties omnigen_instance_id, omnigen_category, omnigen_dims.
- One Principled BSDF material, "omnigen_pbr", whose inputs (base colour, roughness, metallic,
  emission colour and strength) come from per-face attributes (pbr_base, pbr_rme, pbr_emit).
  The materials stay plain data (scenes/materials.py); a frame that changes colours, wetness or
  lights rewrites attributes instead of creating hundreds of datablocks, so nothing leaks and a
  frame update costs milliseconds. A user opening the .blend can still read every value.
- A physical sky (Sky Texture, MULTIPLE_SCATTERING: Blender 5.0's name for the Nishita model)
  mixed towards cloud grey by cloud cover, and a sun lamp placed from the description.
- Fog and haze as a volume: a box (Principled Volume, density = the description's extinction
  coefficient in 1/m) that follows a focus point, like Infinigen's weather that follows the
  camera; `place_weather(focus)` moves it.
- Rain and snow as a documented approximation of a particle system's snapshot: one mesh of
  thin streaks (rain, length of a drop's motion in 1/60 s) or small flakes (snow) drawn from the
  frame's generator in a 60 x 60 x 30 m box around the focus. No simulation cache, deterministic.
  Weather objects have pass_index 0 and the property omnigen_weather (hide them for mask passes).
- Street lamps as spot lights when the description turns them on.
- The camera: an omnigen.camera.Camera, set through its Blender conversions (lens, sensor width
  and shifts with sensor_fit AUTO; matrix_world in Blender camera axes), which are plain numpy.
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
from pathlib import Path

import bpy
import mathutils
import numpy as np

from omnigen.camera import Camera
from omnigen.scenes.cycles_devices import CyclesDevice, DeviceChoice, choose_devices
from omnigen.scenes.description import Material, Scene
from omnigen.scenes.meshes import RenderObject, compile_scene, lamp_lights
from omnigen.scenes.seeding import frame_streams


@contextlib.contextmanager
def _native_output_to(path: str = os.devnull, fds: tuple[int, ...] = (1,)):
    """Send what Blender's C code prints to `path` (file descriptors, past Python's sys.stdout)."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(fd) for fd in fds]
    target = os.open(path, os.O_WRONLY | os.O_APPEND)
    try:
        for fd in fds:
            os.dup2(target, fd)
        yield
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        for fd, s in zip(fds, saved):
            os.dup2(s, fd)
            os.close(s)
        os.close(target)


def _quiet_native_output():
    """Silence what Blender's C code prints during a render ("Saved: ..." per file written by the
    compositor): it goes straight to file descriptor 1, past Python's sys.stdout, and would bury
    the progress bar and summary tables of `omnigen render`."""
    return _native_output_to(os.devnull)


# ---------------------------------------------------------------------------------------------
# Compute devices (--device; the decision is scenes/cycles_devices.py's)
# ---------------------------------------------------------------------------------------------


def _cycles_preferences():
    return bpy.context.preferences.addons["cycles"].preferences


def cycles_devices(requested: str) -> DeviceChoice:
    """Enumerate the devices Cycles sees and decide which a render of kind `requested` uses;
    changes nothing. Raises DeviceUnavailable naming what was found.

    Cycles prints why a GPU library did not load ("CUEW initialization failed: Error opening the
    library") on its first enumeration in a process; that is caught and quoted in the error."""
    import re
    import tempfile

    prefs = _cycles_preferences()
    with tempfile.NamedTemporaryFile("r", prefix="omnigen-cycles-devices-") as log:
        with _native_output_to(log.name, fds=(1, 2)):
            offered = tuple(t for t, *_ in prefs.get_device_types(bpy.context) if t != "NONE")
            listed = [d for t in (*offered, "CPU") for d in prefs.get_device_list(t)]
        # "00:00.594  cycles  | WARNING CUEW initialization failed: ..." -> "CUEW initialization ..."
        said = tuple(re.sub(r"^(WARNING|ERROR)\s+", "", line.split("|", 1)[-1].strip())
                     for line in log.read().splitlines() if "WARNING" in line or "ERROR" in line)
    found = list(dict.fromkeys(CyclesDevice(type=str(d[1]), name=str(d[0]), id=str(d[2])) for d in listed))
    return choose_devices(requested, found, offered, said)


def use_cycles_devices(requested: str, bscene) -> DeviceChoice:
    """Select the devices of `cycles_devices(requested)` in Cycles' preferences (the chosen type's
    GPUs on, every other device off, the CPU too: OptiX cannot render beside it, and a node's
    few CPU cores would hold the GPUs back) and set the scene's device. Preferences are the
    process's, and read_factory_settings resets them: call after it."""
    choice = cycles_devices(requested)
    prefs = _cycles_preferences()
    prefs.compute_device_type = choice.compute_device_type
    if choice.gpu:
        prefs.get_devices_for_type(choice.compute_device_type)  # makes the entries to switch on
    wanted = {(d.type, d.id) for d in choice.devices}
    for entry in prefs.devices:
        entry.use = (entry.type, entry.id) in wanted
    bscene.cycles.device = choice.scene_device
    return choice


PBR = "omnigen_pbr"
AGENTS, STATIC, WEATHER = "omnigen_agents", "omnigen_static", "omnigen_weather"
WEATHER_BOX = (60.0, 60.0, 30.0)
QUALITY = {  # Cycles settings of --quality (docs/rendering.md, "Speed", has the measurements).
    # samples: the most per pixel (adaptive sampling stops earlier where the noise is below
    # adaptive_threshold); bounces: max_bounces, and the diffuse/glossy/transmission caps;
    # denoise: OpenImageDenoise (on the CPU, or on the render's GPU) with the given prefilter and
    # quality (the prefilter ACCURATE denoises the albedo and normal passes too: about 7 s of a
    # 640 x 640 frame on the 2-core machine, against well under a second for FAST); caustics:
    # reflective and refractive.
    # min_volume_density: thinner fog (clear-weather haze, visibility above 2 km) is left out of
    # the beauty render: the 1.5 km haze volume cost 3x the frame time at 256 x 256.
    # light_tree: Cycles' light tree for next-event estimation. The PBR material's emission comes
    # from attributes, so Cycles counts every triangle of the city as a possible light; its tree
    # over them made a 1-sample label pass at 640 x 640 take 1.6 s against 0.8 s without it.
    "preview": {"samples": 2, "denoise": True, "bounces": 1, "adaptive_threshold": 0.1, "caustics": False,
                "light_tree": False, "denoising_prefilter": "FAST", "denoising_quality": "FAST", "min_volume_density": 0.002},
    "fast": {"samples": 4, "denoise": True, "bounces": 2, "adaptive_threshold": 0.05, "caustics": False,
             "light_tree": False, "denoising_prefilter": "FAST", "denoising_quality": "BALANCED", "min_volume_density": 0.002},
    "final": {"samples": 256, "denoise": True, "bounces": 12, "adaptive_threshold": 0.01, "caustics": True,
              "light_tree": True, "denoising_prefilter": "ACCURATE", "denoising_quality": "HIGH", "min_volume_density": 0.0},
}


# ---------------------------------------------------------------------------------------------
# Low-level helpers
# ---------------------------------------------------------------------------------------------


def _mesh_from_parts(name: str, parts: dict) -> tuple[bpy.types.Mesh, list[tuple[str, int]]]:
    """One mesh from role -> trimesh parts; returns it and the (role, face count) order."""
    verts, faces, order, n = [], [], [], 0
    for role, m in parts.items():
        v = np.asarray(m.vertices, dtype=np.float32)
        f = np.asarray(m.faces, dtype=np.int32)
        verts.append(v)
        faces.append(f + n)
        order.append((role, len(f)))
        n += len(v)
    v = np.vstack(verts)
    f = np.vstack(faces)
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(v))
    mesh.vertices.foreach_set("co", v.ravel())
    mesh.loops.add(3 * len(f))
    mesh.loops.foreach_set("vertex_index", f.ravel())
    mesh.polygons.add(len(f))
    mesh.polygons.foreach_set("loop_start", np.arange(0, 3 * len(f), 3, dtype=np.int32))
    mesh.update(calc_edges=True)
    for attr in ("pbr_base", "pbr_rme", "pbr_emit"):
        mesh.attributes.new(attr, "FLOAT_VECTOR", "FACE")
    mesh.materials.append(_pbr_material())
    return mesh, order


def _write_materials(mesh: bpy.types.Mesh, order: list[tuple[str, int]], materials: dict[str, Material]) -> None:
    base, rme, emit = [], [], []
    for role, count in order:
        m = materials[role]
        base.append(np.tile(np.asarray(m.base_color, dtype=np.float32), (count, 1)))
        rme.append(np.tile(np.array([m.roughness, m.metallic, m.emission_strength], dtype=np.float32), (count, 1)))
        emit.append(np.tile(np.asarray(m.emission_color, dtype=np.float32), (count, 1)))
    mesh.attributes["pbr_base"].data.foreach_set("vector", np.vstack(base).ravel())
    mesh.attributes["pbr_rme"].data.foreach_set("vector", np.vstack(rme).ravel())
    mesh.attributes["pbr_emit"].data.foreach_set("vector", np.vstack(emit).ravel())


def _pbr_material() -> bpy.types.Material:
    mat = bpy.data.materials.get(PBR)
    if mat is not None:
        return mat
    mat = bpy.data.materials.new(PBR)
    nt = mat.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
    nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])

    def attr(name: str):
        node = nt.nodes.new("ShaderNodeAttribute")
        node.attribute_type = "GEOMETRY"
        node.attribute_name = name
        return node

    base, rme, emit = attr("pbr_base"), attr("pbr_rme"), attr("pbr_emit")
    nt.links.new(base.outputs["Color"], bsdf.inputs["Base Color"])
    sep = nt.nodes.new("ShaderNodeSeparateXYZ")
    nt.links.new(rme.outputs["Vector"], sep.inputs["Vector"])
    nt.links.new(sep.outputs["X"], bsdf.inputs["Roughness"])
    nt.links.new(sep.outputs["Y"], bsdf.inputs["Metallic"])
    nt.links.new(sep.outputs["Z"], bsdf.inputs["Emission Strength"])
    nt.links.new(emit.outputs["Color"], bsdf.inputs["Emission Color"])
    return mat


def _simple_material(name: str, color, roughness: float = 0.5, transmission: float = 0.0, alpha: float = 1.0) -> bpy.types.Material:
    mat = bpy.data.materials.get(name) or bpy.data.materials.new(name)
    bsdf = mat.node_tree.nodes.get("Principled BSDF")
    if bsdf is None:
        bsdf = mat.node_tree.nodes.new("ShaderNodeBsdfPrincipled")
        out = mat.node_tree.nodes.get("Material Output") or mat.node_tree.nodes.new("ShaderNodeOutputMaterial")
        mat.node_tree.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    bsdf.inputs["Roughness"].default_value = roughness
    bsdf.inputs["Transmission Weight"].default_value = transmission
    bsdf.inputs["Alpha"].default_value = alpha
    return mat


def _collection(name: str) -> bpy.types.Collection:
    col = bpy.data.collections.get(name)
    if col is None:
        col = bpy.data.collections.new(name)
        bpy.context.scene.collection.children.link(col)
    return col


def _remove_object(obj: bpy.types.Object) -> None:
    data = obj.data
    bpy.data.objects.remove(obj, do_unlink=True)
    if data is not None and data.users == 0:
        if isinstance(data, bpy.types.Mesh):
            bpy.data.meshes.remove(data)
        elif isinstance(data, bpy.types.Light):
            bpy.data.lights.remove(data)


def _trim_heap() -> None:
    """Hand freed heap pages back to the system (glibc's malloc_trim), once per frame update. The
    datablock counts stay flat across frames; in a 200-frame run at 96 x 96 resident memory was
    614 MB after frame 20 and 700 after frame 200 without it, 595 and 670 with it (rendering.md)."""
    import ctypes

    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc
        pass


# ---------------------------------------------------------------------------------------------
# The scene
# ---------------------------------------------------------------------------------------------


class BlenderScene:
    """A bpy scene kept in step with a Scene: build once, `update` per frame, `save_blend`."""

    def __init__(self, scene: Scene, reset: bool = True, volumes: bool = True, precipitation: bool = True,
                 device: str = "cpu") -> None:
        if reset:
            bpy.ops.wm.read_factory_settings(use_empty=True)
        self.volumes, self.precipitation = volumes, precipitation
        self.bscene = bpy.context.scene
        self.bscene.render.engine = "CYCLES"
        self.device = use_cycles_devices(device, self.bscene)  # --device (scenes/cycles_devices.py)
        self.bscene.view_layers[0].use_pass_object_index = True
        self.bscene.view_layers[0].use_pass_z = True
        self._order: dict[str, list[tuple[str, int]]] = {}
        self.objects: dict[str, RenderObject] = {}
        self.focus = (0.0, 0.0, 0.0)
        self.scene = scene
        for obj in compile_scene(scene):
            self._add(obj)
        self._environment(scene)

    # -- objects ----------------------------------------------------------------------------

    def _add(self, obj: RenderObject) -> None:
        mesh, order = _mesh_from_parts(obj.name, obj.parts)
        _write_materials(mesh, order, obj.materials)
        bobj = bpy.data.objects.new(obj.name, mesh)
        bobj.matrix_world = _matrix(obj.matrix_world)
        if obj.kind == "agent":
            bobj.pass_index = int(obj.instance_id)
            bobj["omnigen_instance_id"] = int(obj.instance_id)
            bobj["omnigen_category"] = obj.category
            bobj["omnigen_dims"] = [float(d) for d in obj.dims]
        bobj["omnigen_kind"] = obj.kind
        _collection(AGENTS if obj.kind == "agent" else STATIC).objects.link(bobj)
        self._order[obj.name] = order
        self.objects[obj.name] = obj

    def update(self, scene: Scene) -> None:
        """Next frame over the same city: new agents, restyled static objects, new environment."""
        if scene.city is not self.scene.city and scene.city != self.scene.city:
            raise ValueError("BlenderScene.update needs the same city; build a new BlenderScene for another")
        for bobj in list(_collection(AGENTS).objects):
            self._order.pop(bobj.name, None)
            self.objects.pop(bobj.name, None)
            _remove_object(bobj)
        for obj in compile_scene(scene):
            if obj.kind == "agent":
                self._add(obj)
            else:
                _write_materials(bpy.data.objects[obj.name].data, self._order[obj.name], obj.materials)
                self.objects[obj.name] = obj
        self.scene = scene
        self._environment(scene)
        _trim_heap()

    # -- environment ------------------------------------------------------------------------

    def _environment(self, scene: Scene) -> None:
        self._sky(scene)
        self._sun(scene)
        self._lamps(scene)
        self._weather(scene)

    def _sky(self, scene: Scene) -> None:
        light, w = scene.lighting, scene.weather
        world = bpy.data.worlds.get("omnigen_world") or bpy.data.worlds.new("omnigen_world")
        self.bscene.world = world
        nt = world.node_tree
        if "omnigen_sky" not in nt.nodes:
            nt.nodes.clear()
            out = nt.nodes.new("ShaderNodeOutputWorld")
            bg = nt.nodes.new("ShaderNodeBackground")
            bg.name = "omnigen_background"
            sky = nt.nodes.new("ShaderNodeTexSky")
            sky.name = "omnigen_sky"
            sky.sky_type = "MULTIPLE_SCATTERING"
            mix = nt.nodes.new("ShaderNodeMix")
            mix.name = "omnigen_clouds"
            mix.data_type = "RGBA"
            nt.links.new(sky.outputs["Color"], mix.inputs[6])  # A (colour)
            nt.links.new(mix.outputs[2], bg.inputs["Color"])  # Result (colour)
            nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
        sky, mix, bg = nt.nodes["omnigen_sky"], nt.nodes["omnigen_clouds"], nt.nodes["omnigen_background"]
        sky.sun_elevation = math.radians(max(light.sun_elevation, -5.0))
        sky.sun_rotation = sun_rotation_for_azimuth(light.sun_azimuth)
        sky.sun_disc = w.cloud_cover < 0.6
        sky.aerosol_density = 1.0 + 4.0 * min(w.fog_density / 0.01, 1.0)
        grey = 0.35 * max(light.sky_strength, 0.02)
        mix.inputs[0].default_value = float(w.cloud_cover)  # factor
        mix.inputs[7].default_value = (grey, grey * 1.02, grey * 1.06, 1.0)  # B (colour)
        # The physical sky is dark once the sun has set; keep a faint night sky.
        bg.inputs["Strength"].default_value = float(max(light.sky_strength, 0.02)) * (0.6 if light.sun_elevation > 0 else 1.0)

    def _sun(self, scene: Scene) -> None:
        light, w = scene.lighting, scene.weather
        obj = bpy.data.objects.get("omnigen_sun")
        if obj is None:
            data = bpy.data.lights.new("omnigen_sun", "SUN")
            obj = bpy.data.objects.new("omnigen_sun", data)
            _collection(WEATHER).objects.link(obj)
        d = np.asarray(light.sun_direction)
        obj.matrix_world = _matrix(_look_along(-d))
        obj.data.energy = float(light.sun_strength) if light.sun_elevation > 0 else 0.0
        obj.data.angle = math.radians(0.53 + 25.0 * float(w.cloud_cover))
        warm = float(np.clip(1.0 - light.sun_elevation / 20.0, 0.0, 1.0))
        obj.data.color = (1.0, 1.0 - 0.25 * warm, 1.0 - 0.55 * warm)

    def _lamps(self, scene: Scene) -> None:
        for obj in [o for o in _collection(WEATHER).objects if o.get("omnigen_lamp")]:
            _remove_object(obj)
        for lamp in lamp_lights(scene):
            data = bpy.data.lights.new(lamp.name, "SPOT")
            data.energy = lamp.power
            data.color = lamp.color
            data.spot_size = lamp.spot_angle
            data.shadow_soft_size = 0.2
            obj = bpy.data.objects.new(lamp.name, data)
            obj.location = lamp.position  # spots shine along -z: straight down
            obj["omnigen_lamp"] = True
            _collection(WEATHER).objects.link(obj)

    def _weather(self, scene: Scene) -> None:
        for name in ("omnigen_fog", "omnigen_precipitation"):
            obj = bpy.data.objects.get(name)
            if obj is not None:
                _remove_object(obj)
        w = scene.weather
        if self.volumes and w.fog_density > 0:
            self._fog(w.fog_density)
        if self.precipitation and w.precipitation > 0 and w.kind in ("rain", "snow"):
            self._precip(scene)
        self.place_weather(self.focus)

    def _fog(self, density: float) -> None:
        # Big enough that what lies beyond is fully extinct (transmittance < 1%), at most 1.5 km.
        half = float(min(max(4.6 / density, 100.0), 1500.0))
        mesh = bpy.data.meshes.new("omnigen_fog")
        v = np.array([[x, y, z] for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)], dtype=np.float32)
        v = v * np.array([half, half, 150.0], dtype=np.float32) + np.array([0, 0, 148.0], dtype=np.float32)
        faces = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
        mesh.from_pydata(v.tolist(), [], faces)
        mat = bpy.data.materials.get("omnigen_fog") or bpy.data.materials.new("omnigen_fog")
        nt = mat.node_tree
        nt.nodes.clear()
        out = nt.nodes.new("ShaderNodeOutputMaterial")
        vol = nt.nodes.new("ShaderNodeVolumePrincipled")
        vol.inputs["Color"].default_value = (0.85, 0.87, 0.9, 1.0)
        vol.inputs["Density"].default_value = float(density)
        vol.inputs["Anisotropy"].default_value = 0.3
        nt.links.new(vol.outputs["Volume"], out.inputs["Volume"])
        mesh.materials.append(mat)
        obj = bpy.data.objects.new("omnigen_fog", mesh)
        obj["omnigen_weather"] = "fog"
        obj["omnigen_follow"] = True
        _collection(WEATHER).objects.link(obj)

    def _precip(self, scene: Scene) -> None:
        w = scene.weather
        rng = frame_streams(scene.dataset_seed, scene.frame_index)["extra"]
        bx, by, bz = WEATHER_BOX
        rain = w.kind == "rain"
        n = int((6000 if rain else 8000) * w.precipitation)
        p = rng.uniform([-bx / 2, -by / 2, 0.0], [bx / 2, by / 2, bz], size=(n, 3))
        drift = np.array([math.cos(w.wind_direction), math.sin(w.wind_direction), 0.0])
        if rain:
            # A drop falls ~8 m/s: in a 1/60 s exposure it draws a 13 cm streak, slanted by wind.
            length = rng.uniform(0.1, 0.18, n)[:, None]
            axis = np.array([0.0, 0.0, -1.0]) + 0.2 * drift
            axis /= np.linalg.norm(axis)
            side = np.cross(axis, [0.0, 1.0, 0.0]) if abs(axis[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
            side = side / np.linalg.norm(side) * 0.0015
            a, b = p, p + axis * length
            v = np.stack([a - side, a + side, b + side, b - side], axis=1).reshape(-1, 3)
            f = (np.arange(n)[:, None] * 4 + np.array([[0, 1, 2], [0, 2, 3]]).reshape(1, 6)).reshape(-1, 3)
            mat = _simple_material("omnigen_rain", (0.8, 0.82, 0.85), roughness=0.05, transmission=0.9)
        else:
            r = rng.uniform(0.004, 0.012, n)[:, None]
            octa = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64)
            tri = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
            v = (p[:, None, :] + octa[None] * r[:, :, None]).reshape(-1, 3)
            f = (np.arange(n)[:, None, None] * 6 + tri[None]).reshape(-1, 3)
            mat = _simple_material("omnigen_snow", (0.9, 0.9, 0.92), roughness=0.6)
        import trimesh

        mesh, order = _mesh_from_parts("omnigen_precipitation", {"p": trimesh.Trimesh(v, f, process=False)})
        mesh.materials.clear()
        mesh.materials.append(mat)
        obj = bpy.data.objects.new("omnigen_precipitation", mesh)
        obj["omnigen_weather"] = w.kind
        obj["omnigen_follow"] = True
        _collection(WEATHER).objects.link(obj)

    def place_weather(self, focus) -> None:
        """Centre the fog box and the precipitation on `focus` (x, y, z): the camera, usually."""
        self.focus = tuple(float(c) for c in focus)
        for name in ("omnigen_fog", "omnigen_precipitation"):
            obj = bpy.data.objects.get(name)
            if obj is not None:
                z = 0.0 if name == "omnigen_fog" else max(self.focus[2] - WEATHER_BOX[2] / 2, 0.0)
                obj.location = (self.focus[0], self.focus[1], z)

    # -- rendering (Cycles) -----------------------------------------------------------------
    #
    # The beauty render (Cycles at the quality's samples) gives RGB only. Depth and instance ids
    # come from a separate "label pass": Cycles at 1 sample, no bounces, a 0.01 px pixel filter
    # (so each pixel is sampled at its centre, as a rasteriser does, and ids are never blended),
    # weather objects (fog box, rain, snow) hidden. Its Depth pass is camera z (planar, measured
    # against pyrender: median difference 0.3 mm), written with the IndexOB pass by the
    # compositor's File Output node as separate float32 EXRs (bpy 5.0: a multilayer File Output
    # or write_still wrote only the image), then read back with OpenEXR.
    # Silhouettes "drawn alone" are the same label pass with only the given agents visible.

    def set_quality(self, quality: str) -> None:
        if quality not in QUALITY:
            raise ValueError(f"unknown quality {quality!r}; choose from {', '.join(QUALITY)}")
        self.quality = QUALITY[quality]

    def _ensure_render_setup(self) -> None:
        if getattr(self, "_camera_obj", None) is not None and self._camera_obj.name in bpy.data.objects:
            return
        import tempfile

        sc = self.bscene
        data = bpy.data.cameras.new("omnigen_camera")
        self._camera_obj = bpy.data.objects.new("omnigen_camera", data)
        sc.collection.objects.link(self._camera_obj)
        sc.camera = self._camera_obj
        data.sensor_fit = "AUTO"
        data.clip_start, data.clip_end = 0.1, 5000.0
        sc.render.resolution_percentage = 100
        sc.render.use_persistent_data = True
        sc.render.use_compositing = True
        sc.cycles.seed = 0
        self._tmp = tempfile.mkdtemp(prefix="omnigen-cycles-")
        if not hasattr(self, "quality"):
            self.set_quality("fast")
        # beauty: Image -> PNG through the view transform
        ng = bpy.data.node_groups.new("omnigen_beauty", "CompositorNodeTree")
        rl = ng.nodes.new("CompositorNodeRLayers")
        fo = ng.nodes.new("CompositorNodeOutputFile")
        fo.format.media_type = "IMAGE"
        fo.format.file_format = "PNG"
        fo.format.color_mode = "RGB"
        fo.format.color_depth = "8"
        item = fo.file_output_items.new("RGBA", "rgb")
        item.save_as_render = True
        ng.links.new(rl.outputs["Image"], fo.inputs["rgb"])
        fo.directory, fo.file_name = self._tmp, "beauty_"
        self._beauty_tree = ng
        # labels: Depth and Object Index -> float32 EXRs
        ng = bpy.data.node_groups.new("omnigen_labels", "CompositorNodeTree")
        rl = ng.nodes.new("CompositorNodeRLayers")
        fo = ng.nodes.new("CompositorNodeOutputFile")
        fo.format.media_type = "IMAGE"
        fo.format.file_format = "OPEN_EXR"
        fo.format.color_depth = "32"
        fo.format.exr_codec = "NONE"
        for name, out in (("depth", "Depth"), ("index", "Object Index")):
            fo.file_output_items.new("FLOAT", name)
            ng.links.new(rl.outputs[out], fo.inputs[name])
        fo.directory, fo.file_name = self._tmp, "labels_"
        self._label_tree = ng

    def _set_camera(self, camera: Camera) -> None:
        self._ensure_render_setup()
        p = camera.blender_settings()
        data = self._camera_obj.data
        data.lens, data.sensor_width, data.shift_x, data.shift_y = p["lens"], p["sensor_width"], p["shift_x"], p["shift_y"]
        self._camera_obj.matrix_world = _matrix(camera.blender_matrix_world())
        sc = self.bscene
        sc.render.resolution_x, sc.render.resolution_y = camera.width, camera.height

    def _run(self, tree) -> None:
        for f in os.listdir(self._tmp):
            os.unlink(os.path.join(self._tmp, f))
        self.bscene.compositing_node_group = tree
        with _quiet_native_output():
            bpy.ops.render.render(write_still=False)

    def render(self, camera: Camera, labels: bool = True) -> dict:
        """Cycles RGB (uint8 sRGB through the view transform) plus the label pass's depth (camera z,
        inf where nothing was hit) and instance ids (None with labels=False: the caller draws them
        another way); `seconds` is the beauty render's time."""
        import time as _time

        from PIL import Image

        self._set_camera(camera)
        self.place_weather(tuple(float(v) for v in camera.center))
        self._apply_quality()
        fog = bpy.data.objects.get("omnigen_fog")
        skip_fog = fog is not None and self.scene.weather.fog_density < self.quality["min_volume_density"]
        if skip_fog:
            fog.hide_render = True
        t0 = _time.perf_counter()
        try:
            self._run(self._beauty_tree)
            seconds = _time.perf_counter() - t0
            with Image.open(self._single("beauty_")) as img:
                rgb = np.asarray(img.convert("RGB")).copy()
            # The label pass runs before the fog comes back: with the same objects visible as in
            # the beauty render, Cycles (persistent data) reuses the beauty render's BVH instead
            # of building the city's again (about 2 s at 640 x 640 on the 2-core machine).
            depth, instance = self._labels(None) if labels else (None, None)
        finally:
            if skip_fog:
                fog.hide_render = False
        return {"rgb": rgb, "depth": depth, "instance": instance, "seconds": seconds}

    def _apply_quality(self) -> None:
        c, q = self.bscene.cycles, self.quality
        c.samples, c.use_denoising, c.max_bounces = q["samples"], q["denoise"], q["bounces"]
        c.diffuse_bounces = c.glossy_bounces = c.transmission_bounces = q["bounces"]
        c.caustics_reflective = c.caustics_refractive = q["caustics"]
        c.use_light_tree = q["light_tree"]
        c.use_adaptive_sampling, c.adaptive_threshold = True, q["adaptive_threshold"]
        # OpenImageDenoise on the render's GPU when it has one (same denoiser, results equal but
        # for float rounding); on the CPU otherwise.
        c.denoiser, c.denoising_use_gpu = "OPENIMAGEDENOISE", self.device.gpu
        c.denoising_prefilter, c.denoising_quality = q["denoising_prefilter"], q["denoising_quality"]
        c.filter_width = 1.5

    def render_instances(self, camera: Camera, instance_ids) -> np.ndarray:
        """Instance ids of only the given agents, nothing else drawn (the label pass)."""
        self._set_camera(camera)
        return self._labels({int(i) for i in instance_ids})[1]

    def _single(self, prefix: str, name: str = "") -> str:
        import os

        files = sorted(f for f in os.listdir(self._tmp) if f.startswith(prefix + name))
        if not files:
            raise RuntimeError(f"Blender wrote no {prefix}{name} file in {self._tmp}")
        return os.path.join(self._tmp, files[0])

    def _labels(self, only_ids: set[int] | None) -> tuple[np.ndarray, np.ndarray]:
        import OpenEXR

        c = self.bscene.cycles
        saved = (c.samples, c.use_denoising, c.max_bounces, c.filter_width, c.use_adaptive_sampling, c.use_light_tree)
        c.samples, c.use_denoising, c.max_bounces, c.filter_width, c.use_adaptive_sampling = 1, False, 0, 0.01, False
        c.use_light_tree = False  # only depth and ids are kept: no need for a good light choice
        hidden = []
        for obj in self.bscene.objects:
            if obj.type == "LIGHT":
                # Depth and ids need no light: without the sun and lamps Cycles traces no shadow
                # rays for them, a large part of this one-sample pass. Showing them again costs
                # the next beauty render only a light-table update, not a BVH rebuild.
                hide = True
            elif obj.type != "MESH":
                continue
            else:
                hide = obj.get("omnigen_weather") is not None
            if only_ids is not None and obj.type == "MESH":
                hide = int(obj.get("omnigen_instance_id", 0)) not in only_ids
            if hide and not obj.hide_render:
                obj.hide_render = True
                hidden.append(obj)
        try:
            self._run(self._label_tree)
        finally:
            for obj in hidden:
                obj.hide_render = False
            c.samples, c.use_denoising, c.max_bounces, c.filter_width, c.use_adaptive_sampling, c.use_light_tree = saved
        out = []
        for name in ("depth", "index"):
            with OpenEXR.File(self._single("labels_", name), separate_channels=True) as f:
                ch = f.channels()
                key = "R" if "R" in ch else ("V" if "V" in ch else next(iter(ch)))
                out.append(np.asarray(ch[key].pixels, dtype=np.float32).copy())
        depth, index = out
        depth[depth >= 1e9] = np.inf
        return depth, np.rint(index).astype(np.uint16)

    # -- inspection and output ----------------------------------------------------------------

    def objects_summary(self) -> list[dict]:
        """Name, instance id, class and world box of every scene object, read back from bpy."""
        out = []
        for col in (STATIC, AGENTS):
            for bobj in _collection(col).objects:
                mesh = bobj.data
                co = np.empty(3 * len(mesh.vertices), dtype=np.float32)
                mesh.vertices.foreach_get("co", co)
                co = co.reshape(-1, 3).astype(np.float64)
                lo, hi = co.min(axis=0), co.max(axis=0)
                m = np.array(bobj.matrix_world)
                center = m @ np.append((lo + hi) / 2.0, 1.0)
                iid = int(bobj.get("omnigen_instance_id", 0))
                out.append({"name": bobj.name, "instance_id": iid, "category": bobj.get("omnigen_category"),
                            "center": center[:3].tolist(), "dims": (hi - lo).tolist(), "yaw": math.atan2(m[1, 0], m[0, 0])})
        return out

    def environment_objects(self) -> list[dict]:
        """Sun, lamps, fog and precipitation: name, role and location (for checks and tools)."""
        out = []
        for obj in _collection(WEATHER).objects:
            role = "lamp" if obj.get("omnigen_lamp") else obj.get("omnigen_weather", "sun" if obj.name == "omnigen_sun" else "")
            out.append({"name": obj.name, "role": role, "location": tuple(obj.location)})
        return out

    def datablock_counts(self) -> dict[str, int]:
        """How many meshes, objects, lights and materials exist: flat across frames, or a leak."""
        return {"meshes": len(bpy.data.meshes), "objects": len(bpy.data.objects), "lights": len(bpy.data.lights),
                "materials": len(bpy.data.materials), "images": len(bpy.data.images)}

    def save_blend(self, path: str | Path) -> Path:
        """Write the scene as a .blend a user opens in Blender (relative paths, compressed)."""
        path = Path(path).resolve()
        path.parent.mkdir(parents=True, exist_ok=True)
        bpy.ops.wm.save_as_mainfile(filepath=str(path), check_existing=False, compress=True, copy=True)
        return path


def sun_rotation_for_azimuth(azimuth_deg: float) -> float:
    """Sky Texture's sun_rotation (radians) for an azimuth clockwise from north (+y) to east (+x).

    Measured on bpy 5.0.1 (an equirectangular render of the sky): rotation 0 puts the sun at +y,
    90 degrees at +x, so the two agree. test_scene_blender.py renders the sky to keep it so.
    """
    return float(math.radians(azimuth_deg)) % (2 * math.pi)


def _matrix(m: np.ndarray) -> mathutils.Matrix:
    """A 4x4 numpy matrix (rows) as Blender's Matrix. Assigning nested lists to matrix_world
    would be read column by column, i.e. transposed."""
    return mathutils.Matrix([[float(v) for v in row] for row in np.asarray(m)])


def _look_along(direction) -> np.ndarray:
    """4x4 whose -z axis points along `direction` (Blender lamps shine along their -z)."""
    d = np.asarray(direction, dtype=np.float64)
    z = -d / np.linalg.norm(d)
    helper = np.array([0.0, 0.0, 1.0]) if abs(z[2]) < 0.99 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2] = x, y, z
    return m


def sky_sun_azimuth_probe(elevation_deg: float, azimuth_deg: float, width: int = 72) -> float:
    """Render the sky alone (equirectangular, Cycles, a few samples) and return the azimuth in
    degrees (clockwise from north) of its brightest pixel: a check of the sky's orientation.

    Uses a temporary scene and world, removed afterwards; the current scene is left as it was.
    """
    import tempfile

    height = width // 2
    previous = bpy.context.window.scene if bpy.context.window else bpy.context.scene
    sc = bpy.data.scenes.new("omnigen_sky_probe")
    world = bpy.data.worlds.new("omnigen_sky_probe")
    sc.world = world
    nt = world.node_tree
    nt.nodes.clear()
    out, bg, sky = nt.nodes.new("ShaderNodeOutputWorld"), nt.nodes.new("ShaderNodeBackground"), nt.nodes.new("ShaderNodeTexSky")
    sky.sky_type = "MULTIPLE_SCATTERING"
    sky.sun_elevation = math.radians(elevation_deg)
    sky.sun_rotation = sun_rotation_for_azimuth(azimuth_deg)
    nt.links.new(sky.outputs["Color"], bg.inputs["Color"])
    nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
    cam_data = bpy.data.cameras.new("omnigen_sky_probe")
    cam_data.type = "PANO"
    cam_data.panorama_type = "EQUIRECTANGULAR"
    cam = bpy.data.objects.new("omnigen_sky_probe", cam_data)
    sc.collection.objects.link(cam)
    # Looking along +x (north is then to the left, at a quarter of the width), up +z.
    cam.matrix_world = _matrix(np.array([[0, 0, -1, 0], [-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1.0]]))
    sc.camera = cam
    sc.render.engine = "CYCLES"
    sc.cycles.samples = 2
    sc.cycles.use_denoising = False
    sc.render.resolution_x, sc.render.resolution_y, sc.render.resolution_percentage = width, height, 100
    sc.render.image_settings.file_format = "OPEN_EXR"
    with tempfile.TemporaryDirectory() as tmp:
        sc.render.filepath = str(Path(tmp) / "sky.exr")
        with _quiet_native_output():
            bpy.ops.render.render(write_still=True, scene=sc.name)
        img = bpy.data.images.load(sc.render.filepath)
        px = np.array(img.pixels[:], dtype=np.float32).reshape(height, width, 4)
        bpy.data.images.remove(img)
    for block, coll in ((cam, bpy.data.objects), (cam_data, bpy.data.cameras), (world, bpy.data.worlds), (sc, bpy.data.scenes)):
        coll.remove(block)
    if bpy.context.window is not None:
        bpy.context.window.scene = previous
    col = int(np.argmax(px[..., :3].sum(axis=-1).max(axis=0)))
    # Column c looks at angle (c + 0.5)/width * 360 - 180 from forward (+x), counter-clockwise
    # to the left; azimuth is clockwise from north: az = 90 - that angle.
    left_of_x = 180.0 - (col + 0.5) / width * 360.0
    return (90.0 - left_of_x) % 360.0
