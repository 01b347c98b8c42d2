"""The Blender backend: RenderObjects as a bpy scene. The only module in omnigen importing bpy.

What it builds, and why this way:
- Meshes from numpy with foreach_set (no bpy.ops), flat-shaded, one object per RenderObject,
  named as in the description; agents carry pass_index = instance id (Cycles' IndexOB pass) and
  custom properties omnigen_instance_id, omnigen_category, omnigen_dims.
- Datablocks made once and reused from frame to frame (BlenderScene): a pool of agent objects
  whose meshes are rewritten in place, the street lamps, fog box and precipitation shown or
  hidden, the static city restyled where its colours change; nothing is deleted per frame, and
  a frame renders the bytes a fresh process rendering only that frame renders.
- Two Principled BSDF materials whose inputs (base colour, roughness, metallic, emission colour
  and strength) come from per-face attributes (pbr_base, pbr_rme, pbr_emit): "omnigen_pbr" for
  plain parts (car paint with a clear coat) and "omnigen_surface" for the procedural surfaces of
  materials.Surface (asphalt with the city's road wear, paving, grass, facades, roofs, windows...),
  the raster shader's surface() as shader nodes over two packed images made once per build (the
  noise table and the road-wear map); the pattern of each face is an attribute too (pbr_surface,
  pbr_amp, pbr_cell), written once. The materials stay plain data (scenes/materials.py); a frame
  that changes colours, wetness or lights rewrites attributes instead of creating hundreds of
  datablocks, so nothing leaks and a frame update costs milliseconds. A user opening the .blend
  can still read every value.
- A physical sky (Sky Texture, MULTIPLE_SCATTERING: Blender 5.0's name for the Nishita model; its
  sun disc dark, the lamp is the sun) mixed towards an even grey by cloud cover and scaled to the
  raster's share of the daylight (sky_irradiance, daylight), and a sun lamp placed from the
  description.
- The camera of the raster (expose): Cycles writes linear radiance (and depth); the raster's
  daylight exposure, an automatic exposure metered on the road (ROAD_KEY) and the raster's
  sRGB and tone curve make the 8-bit frame, so asphalt reads as asphalt, not near white.
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
import time
from dataclasses import replace
from functools import partial
from pathlib import Path

import bpy
import mathutils
import numpy as np

from omnigen.camera import Camera
from omnigen.scenes.cycles_devices import CyclesDevice, DeviceChoice, choose_devices
from omnigen.scenes.description import Material, Scene
from omnigen.scenes.materials import NOISE_SIZE, PATTERNS, SURFACE_WEIGHTS, Surface, noise_table, part_surface
from omnigen.scenes.meshes import RenderObject, compile_scene, lamp_lights
from omnigen.scenes.road_wear import WEAR_RUBBER, WEAR_STAIN, road_wear_map
from omnigen.scenes.seeding import instant_extra_rng


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
# Light and exposure: the raster's camera (raster_backend.illumination, gl_raster.auto_exposure)
# ---------------------------------------------------------------------------------------------
#
# Cycles' light is made to agree with the raster's: the sun lamp gives Lighting.sun_strength (W/m^2
# on a face square to it), the sky a share of the daylight on a horizontal face (daylight), so a
# clear day's shade is deep and an overcast day is lit mostly by the sky. The camera then does what
# the raster's does, on the linear frame Cycles wrote (BlenderScene.render): a daylight exposure
# that puts a white horizontal face in the frame's daylight at EXPOSURE_KEY (at most MAX_EXPOSURE:
# the night stays dark), an automatic exposure that opens up, at most AE_MAX_GAIN, for a frame
# whose road reads darker than ROAD_KEY, and the raster's output encoding (sRGB, then the tone curve
# TONE_CONTRAST). Numbers are the raster's, in its units (its radiance is SUN_SCALE times
# Blender's); raster_backend imports OpenGL, so they are repeated here and
# tests/scenes/test_cycles_realism.py keeps the two equal.
SUN_SCALE = 0.9
CLEAR_SKY_LIGHT, OVERCAST_SKY_LIGHT = 0.10, 0.6  # the sky's light on a horizontal face, of Lighting.sky_strength
MIN_SKY_STRENGTH = 0.02  # a faint night sky
EXPOSURE_KEY, MAX_EXPOSURE, MIN_EXPOSURE = 1.3, 5.0, 0.2
AE_TARGET, AE_MAX_GAIN, AE_STRIDE = 0.18, 4.0, 4
ROAD_KEY = 0.12
"""Where Cycles' camera differs from the raster's: its automatic exposure meters the road (the
pixels within ROAD_BAND of z = 0, the road's top: asphalt and its markings; sidewalks and lots
stand a kerb higher) and opens up, at most AE_MAX_GAIN past the daylight exposure, until the
road's median reads ROAD_KEY (linear; about 91 of 255 once encoded: KITTI's asphalt frame, 000001,
reads 87 on the road ahead), as a road camera exposes for the road. Metered over the whole frame
(the raster's rule) or over all the ground, the sky, sunlit facades and pale sidewalks held the
exposure down and the asphalt (albedo 0.077, darker under wear) came out at 40-80 of 255, under
KITTI's road (bench_realism's road rows); metered to middle grey (0.18) the road read 115 and
the frames' mean luminance 128-142 against KITTI's 90."""
ROAD_BAND = 0.05  # m above or below z = 0: the road and its markings (1 cm up), not the kerb (15 cm)
MIN_ROAD = 0.02  # the least share of the metered pixels that must show road to meter it
TONE_CONTRAST = 0.5
CAMERA_SKY_GAIN = 2.0
"""The sky as camera rays see it, of the sky that lights the scene: the physical sky's clear horizon
reads about 0.3 of a white sunlit face's light, the raster's (and KITTI's near-white skies) 0.6."""
# The horizontal irradiance of Blender 5.0's MULTIPLE_SCATTERING sky (no sun disc, or one of
# intensity 0: the same; strength 1): its luminance on a white plane (pi times the plane's
# radiance), measured with Cycles (64 samples, a 4 x 4 orthographic view of the plane) by sun
# elevation (degrees) and aerosol density; test_cycles_realism.py measures one entry again.
SKY_ELEVATIONS = (-5.0, 0.0, 2.0, 5.0, 10.0, 15.0, 20.0, 30.0, 45.0, 60.0, 90.0)
SKY_AEROSOLS = (1.0, 3.0, 5.0)
SKY_IRRADIANCE = (
    (0.0491, 1.3342, 2.6750, 4.6604, 7.1231, 8.7044, 9.8150, 11.4048, 13.1083, 14.2661, 15.1928),
    (0.0552, 1.2847, 2.6907, 5.0266, 8.2792, 10.5547, 12.2143, 14.5576, 16.9792, 18.6221, 19.8288),
    (0.0611, 1.2366, 2.6655, 5.2073, 9.0848, 11.9963, 14.1950, 17.3687, 20.5004, 22.5764, 24.1204),
)


def _luminance(c) -> float:
    return float(np.dot(np.asarray(c, dtype=np.float64)[:3], (0.2126, 0.7152, 0.0722)))


def _sun_color(elevation: float) -> tuple[float, float, float]:
    """The sun lamp's colour: orange when low (raster_backend._sun_color)."""
    warm = float(np.clip(1.0 - elevation / 20.0, 0.0, 1.0))
    return (1.0, 1.0 - 0.25 * warm, 1.0 - 0.55 * warm)


def sky_irradiance(elevation: float, aerosol: float) -> float:
    """SKY_IRRADIANCE at a sun elevation (degrees) and aerosol density, bilinearly."""
    by_aerosol = [np.interp(elevation, SKY_ELEVATIONS, row) for row in SKY_IRRADIANCE]
    return float(np.interp(aerosol, SKY_AEROSOLS, by_aerosol))


def daylight(scene: Scene) -> tuple[float, float]:
    """(E_sun, E_sky): the sun lamp's and the sky's light on a horizontal face (luminance, W/m^2 in
    Blender's units), as raster_backend.daylight has them: a cloudless sky gives CLEAR_SKY_LIGHT of
    Lighting.sky_strength, an overcast one OVERCAST_SKY_LIGHT."""
    light, w = scene.lighting, scene.weather
    sun = max(light.sun_strength, 0.0) if light.sun_elevation > 0 else 0.0
    e_sun = sun * max(math.sin(math.radians(light.sun_elevation)), 0.0) * _luminance(_sun_color(light.sun_elevation))
    share = CLEAR_SKY_LIGHT + (OVERCAST_SKY_LIGHT - CLEAR_SKY_LIGHT) * float(w.cloud_cover)
    return e_sun, math.pi * max(light.sky_strength, MIN_SKY_STRENGTH) * share / SUN_SCALE


def exposure(scene: Scene) -> tuple[float, float]:
    """(gain, max_gain): the daylight exposure (linear Cycles radiance -> the frame's linear value)
    and how far the automatic exposure may open up past it (raster_backend.illumination). With the
    sun up it may open the full AE_MAX_GAIN: MAX_EXPOSURE is there to keep the night dark, and
    under an overcast sky it held a street canyon's road at 50-65 of 255 (the canyon sees a third
    to a half of the sky that the daylight exposure counts)."""
    e_sun, e_sky = daylight(scene)
    white = SUN_SCALE * (e_sun + e_sky) / math.pi  # a white horizontal face's radiance, the raster's units
    raster = max(min(EXPOSURE_KEY / max(white, 1e-6), MAX_EXPOSURE), MIN_EXPOSURE)
    day = scene.lighting.sun_elevation > 0.0
    return SUN_SCALE * raster, AE_MAX_GAIN if day else min(AE_MAX_GAIN, MAX_EXPOSURE / raster)


def auto_exposure(linear: np.ndarray, max_gain: float, target: float = AE_TARGET) -> float:
    """The gain g in [1, max_gain] that brings the mean linear luminance of the metered pixels
    (every AE_STRIDE-th of every AE_STRIDE-th row; saturated ones count as 1) up to `target`: the
    raster's rule (gl_raster.auto_exposure), on the exposed linear frame."""
    y = np.asarray(linear[::AE_STRIDE, ::AE_STRIDE, :3], dtype=np.float64) @ (0.2126, 0.7152, 0.0722)
    y = np.minimum(y.ravel(), 1.0)
    if max_gain <= 1.0 or y.size == 0 or y.mean() >= target:
        return 1.0
    lo, hi = 1.0, float(max_gain)
    if np.minimum(y * hi, 1.0).mean() > target:
        for _ in range(24):  # the mean of min(g y, 1) grows with g: bisect
            g = 0.5 * (lo + hi)
            lo, hi = (lo, g) if np.minimum(y * g, 1.0).mean() > target else (g, hi)
    return hi


def road_pixels(camera: Camera, depth: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels whose surface lies within ROAD_BAND of z = 0 (the road and its
    markings), from the beauty render's depth (camera z)."""
    v, u = np.mgrid[0:camera.height, 0:camera.width]
    rays = np.stack([u, v, np.ones_like(u)], axis=-1).astype(np.float64) @ np.linalg.inv(camera.K).T
    hit = np.isfinite(depth) & (depth < 1e9)
    z = camera.center[2] + np.where(hit, depth, 0.0) * (rays @ camera.R)[..., 2]  # world z of centre + depth R^T d
    return hit & (np.abs(z) < ROAD_BAND)


def road_exposure(linear: np.ndarray, max_gain: float, road: np.ndarray) -> float:
    """The gain g in [1, max_gain] that brings the median linear luminance of the road's pixels
    (every AE_STRIDE-th of every AE_STRIDE-th row) up to ROAD_KEY; where the frame shows too little
    road to meter (under MIN_ROAD of its metered pixels), the raster's rule (auto_exposure)."""
    y = np.asarray(linear[::AE_STRIDE, ::AE_STRIDE, :3], dtype=np.float64) @ (0.2126, 0.7152, 0.0722)
    r = road[::AE_STRIDE, ::AE_STRIDE]
    if r.mean() < MIN_ROAD:
        return auto_exposure(linear, max_gain)
    return float(np.clip(ROAD_KEY / max(float(np.median(np.minimum(y[r], 1.0))), 1e-9), 1.0, max(max_gain, 1.0)))


def encode(linear: np.ndarray) -> np.ndarray:
    """Linear RGB -> 8-bit code values: sRGB (IEC 61966-2-1), then the camera's tone curve
    v + TONE_CONTRAST (smoothstep(v) - v) (gl_raster.encode)."""
    c = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    v = np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1.0 / 2.4) - 0.055)
    v = v + TONE_CONTRAST * (v * v * (3.0 - 2.0 * v) - v)
    return np.round(255.0 * v).astype(np.uint8)


def develop_frame(linear: np.ndarray, beauty_depth: np.ndarray, camera: Camera, scene: Scene) -> tuple[np.ndarray, float]:
    """A Cycles frame's image and gain from its beauty render's linear RGB and depth: exposed on
    its road pixels (road_pixels) and encoded (expose)."""
    return expose(linear, scene, road_pixels(camera, beauty_depth))


def expose(linear: np.ndarray, scene: Scene, road: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """A Cycles frame (linear RGB) as the camera records it: uint8 RGB and the total gain applied
    (the daylight exposure times the automatic one, metered on the `road` pixels when given,
    else the raster's rule over the whole frame)."""
    gain, max_gain = exposure(scene)
    exposed = np.asarray(linear, dtype=np.float32)[..., :3] * np.float32(gain)
    auto = auto_exposure(exposed, max_gain) if road is None else road_exposure(exposed, max_gain, road)
    return encode(exposed * np.float32(auto)), gain * auto


# ---------------------------------------------------------------------------------------------
# Low-level helpers
# ---------------------------------------------------------------------------------------------


PBR_ATTRIBUTES = ("pbr_base", "pbr_rme", "pbr_emit")


def _stack_parts(parts: dict) -> tuple[np.ndarray, np.ndarray, list[tuple[str, int]]]:
    """Role -> trimesh parts as one vertex array (float32), one triangle array (int32, into it)
    and the (role, face count) order, written into arrays sized up front (float64 vertices
    rounded to float32 as astype rounds them): converting each part and then stacking the
    copies took about twice as long (a downtown frame's agents: 15-19 ms against 10-11)."""
    sizes = [(len(m.vertices), len(m.faces)) for m in parts.values()]
    v = np.empty((sum(n for n, _ in sizes), 3), dtype=np.float32)
    f = np.empty((sum(k for _, k in sizes), 3), dtype=np.int32)
    order, n, k = [], 0, 0
    for (role, m), (nv, nf) in zip(parts.items(), sizes):
        v[n:n + nv] = m.vertices
        f[k:k + nf] = m.faces
        f[k:k + nf] += n
        order.append((role, nf))
        n, k = n + nv, k + nf
    return v, f, order


def _set_triangles(mesh: bpy.types.Mesh, v: np.ndarray, f: np.ndarray) -> None:
    """Make `mesh` hold the triangles (v, f), replacing what it held: a reused mesh keeps its
    datablock and material slots, and loses its face attributes (clear_geometry), so it ends
    exactly as a new mesh given the same triangles would."""
    if len(mesh.vertices) or len(mesh.polygons):
        mesh.clear_geometry()
    mesh.vertices.add(len(v))
    mesh.loops.add(3 * len(f))
    # Positions and corner vertices through the attributes that store them (bpy 5): the values
    # mesh.vertices' "co" and mesh.loops' "vertex_index" would write, at a tenth of the cost
    # (~70 ms a downtown frame's agents through those; tests/scenes/test_blender_reuse.py).
    mesh.attributes["position"].data.foreach_set("vector", v.ravel())
    mesh.attributes[".corner_vert"].data.foreach_set("value", f.ravel())
    mesh.polygons.add(len(f))
    mesh.polygons.foreach_set("loop_start", np.arange(0, 3 * len(f), 3, dtype=np.int32))
    mesh.update(calc_edges=True)


def _set_materials(mesh: bpy.types.Mesh, materials: list[bpy.types.Material]) -> None:
    """The mesh's material slots, left alone when they already are `materials` (a slot change
    makes Blender rebuild its dependency graph's relations)."""
    if [m.name for m in mesh.materials if m is not None] != [m.name for m in materials] or len(mesh.materials) != len(materials):
        mesh.materials.clear()
        for m in materials:
            mesh.materials.append(m)


class _Painted:
    """A mesh whose faces take their part's Material (pbr_* attributes), written only when a
    role's Material changed (a static building keeps its colours from one clear frame to the
    next), as arrays gathered from a table with one row a role."""

    def __init__(self, mesh: bpy.types.Mesh, order: list[tuple[str, int]]) -> None:
        self.mesh = mesh
        self.roles = tuple(role for role, _ in order)
        self.face_role = np.repeat(np.arange(len(order), dtype=np.int32), [count for _, count in order])
        self.written: dict[str, tuple] = {}  # attribute -> the per-role values it holds
        self.shape: tuple | None = None  # an agent mesh's shape (_shape), what another agent's must equal to take it
        self.parts: dict | None = None  # the parts whose vertices it holds (an agent mesh)

    def paint(self, materials: dict[str, Material]) -> bool:
        """Write the faces' attributes for `materials` (role -> Material); False when nothing changed."""
        mats = [materials[role] for role in self.roles]
        changed = False
        for attr, values in zip(PBR_ATTRIBUTES, _pbr_rows(mats)):
            if self.written.get(attr) == values:
                continue
            table = np.array(values, dtype=np.float32).reshape(len(mats), 3)
            self.mesh.attributes[attr].data.foreach_set("vector", table[self.face_role].ravel())
            self.written[attr] = values
            changed = True
        return changed


def _pbr_rows(mats: list[Material]) -> tuple[tuple, tuple, tuple]:
    """(base colours, (roughness, metallic, emission strength), emission colours), one row a role."""
    base = tuple(tuple(m.base_color) for m in mats)
    rme = tuple((m.roughness, m.metallic, m.emission_strength) for m in mats)
    emit = tuple(tuple(m.emission_color) for m in mats)
    return base, rme, emit


def _paint_mesh(mesh: bpy.types.Mesh, parts: dict, surfaces: dict[str, Surface]) -> _Painted:
    """Fill `mesh` (new or reused) from role -> trimesh parts, ready for _Painted.paint.

    `surfaces` (role -> materials.Surface) become a per-face attribute the surface materials read
    (pbr_surface: pattern, scale, variant, spacing), written with the triangles: a part's pattern
    follows its shape, not the frame. Faces of a patterned role use their pattern's surface
    material, the rest omnigen_pbr, so plain parts (most of an agent) pay nothing for the patterns."""
    return _build_mesh(mesh, *_stack_parts(parts), surfaces)


def _build_mesh(mesh: bpy.types.Mesh, v: np.ndarray, f: np.ndarray, order: list[tuple[str, int]],
                surfaces: dict[str, Surface]) -> _Painted:
    """_paint_mesh from parts already stacked (_stack_parts)."""
    _set_triangles(mesh, v, f)
    for attr in PBR_ATTRIBUTES:
        mesh.attributes.new(attr, "FLOAT_VECTOR", "FACE")
    painted = _Painted(mesh, order)
    _write_surfaces(painted, surfaces)
    return painted


def _set_positions(mesh: bpy.types.Mesh, v: np.ndarray) -> None:
    """Move the vertices of `mesh` to `v` (float32, as many as it has), its triangles kept: what
    _set_triangles with the same triangles makes, without rebuilding the triangles, edges and
    face attributes. mesh.update() marks the normals, bounds and evaluated copy stale."""
    mesh.attributes["position"].data.foreach_set("vector", v.ravel())
    mesh.update()


def _shape(v: np.ndarray, f: np.ndarray, order: list[tuple[str, int]], looks: tuple) -> tuple:
    """What an agent mesh holds besides its vertex positions: its vertex count, its parts' roles
    and triangle counts, its triangles, and each role's surface (`looks`, _looks of them: pattern
    and numbers, hence its material slots). Two agents of one shape differ in positions alone (an
    asset fitted to other dims)."""
    return (len(v), tuple(order), looks, f.tobytes())


def _looks(surfaces: dict[str, Surface]) -> tuple:
    """Each role's surface, pattern and numbers, in the roles' order (the parts' order)."""
    return tuple((role, surface.pattern, surface.row()) for role, surface in surfaces.items())


POOL_SHARE = 1.5  # agent meshes kept, as a multiple of the most agents a frame has had (_AgentMeshes)


class _AgentMeshes:
    """The agents' meshes, kept by shape from frame to frame and lent to the frame's agents.

    Why: an agent's mesh is new every frame (its dims are drawn anew) but its shape (_shape) is
    its asset's, and a frame's agents come in far fewer shapes than agents, so most find a mesh of
    their shape that the last frames left (bench_render.py prints how many a frame are moved and
    built), and take only their vertex positions (_set_positions), where
    a mesh rebuilt for another shape pays for its triangles, edges, face offsets and attributes
    (bench_render.py --profile: _place_agents). A mesh so moved holds exactly what a new one
    would (tests/scenes/test_blender_reuse.py). At most POOL_SHARE times the most agents a frame
    has had are kept, so memory has a bound; past it, a mesh no agent of the frame takes is
    rebuilt for another shape. Nothing is ever deleted (a datablock removal scans all of them)."""

    def __init__(self) -> None:
        self.meshes: list[_Painted] = []
        self.most = 0
        self._spare: list[_Painted] = []  # this frame's meshes no agent took (lend)
        self.built = 0  # meshes built or rebuilt (new shapes), a count for tests and profiles
        self.moved = 0  # meshes that took another agent's positions

    def lend(self, shapes: list[tuple], held: list[_Painted | None]) -> list[_Painted | None]:
        """A kept mesh of each agent's shape, else None (`fresh` makes one); `held[j]`, the mesh
        slot j showed last frame, is preferred, sparing the object a new mesh."""
        self.most = max(self.most, len(shapes))
        free: dict[tuple, list[_Painted]] = {}
        for m in self.meshes:
            free.setdefault(m.shape, []).append(m)
        used: set[int] = set()
        out: list[_Painted | None] = [None] * len(shapes)
        for j, shape in enumerate(shapes):
            m = held[j] if j < len(held) else None
            if m is not None and m.shape == shape:
                out[j] = m
                used.add(id(m))
        for j, shape in enumerate(shapes):
            if out[j] is None:
                kept = free.get(shape, [])
                while kept and id(kept[-1]) in used:
                    kept.pop()
                if kept:
                    out[j] = kept.pop()
                    used.add(id(out[j]))
        self._spare = [m for m in self.meshes if id(m) not in used]
        return out

    def fresh(self, name: str) -> bpy.types.Mesh:
        """A mesh to build another shape into: a new one while the pool is under its bound, else
        one no agent of this frame took (lend must have run for the frame)."""
        self.built += 1
        if len(self.meshes) < math.ceil(POOL_SHARE * self.most) or not self._spare:
            return bpy.data.meshes.new(name)
        painted = self._spare.pop()
        self.meshes.remove(painted)
        return painted.mesh

    def keep(self, painted: _Painted) -> None:
        self.meshes.append(painted)


PLAIN_PATTERNS = frozenset({"plain", "car_paint"})  # drawn by omnigen_pbr (car paint: its coat)


def _write_surfaces(painted: _Painted, surfaces: dict[str, Surface]) -> None:
    """Each face's surface row (pbr_surface) and material slot: omnigen_pbr for plain parts, the
    pattern's surface material for the rest (slots in the order the patterns first appear)."""
    mesh, roles = painted.mesh, painted.roles
    rows = np.array([surfaces[role].row() for role in roles], dtype=np.float32).reshape(len(roles), 4)
    mesh.attributes.new("pbr_surface", "FLOAT_COLOR", "FACE").data.foreach_set("color", rows[painted.face_role].ravel())
    slots = {}
    for role in roles:
        pattern = surfaces[role].pattern
        if pattern not in PLAIN_PATTERNS and pattern not in slots:
            slots[pattern] = len(slots) + 1
    _set_materials(mesh, [_pbr_material(), *(_surface_material(p) for p in slots)])
    if slots:
        index = np.array([slots.get(surfaces[role].pattern, 0) for role in roles], dtype=np.int32)
        mesh.polygons.foreach_set("material_index", index[painted.face_role])


def _pbr_nodes(mat: bpy.types.Material):
    """A material's Principled BSDF fed by the per-face attributes (base colour, roughness,
    metallic, emission), and the base colour's attribute node: the part both materials share."""
    nt = mat.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    bsdf = nt.nodes.new("ShaderNodeBsdfPrincipled")
    nt.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    base, rme, emit = (_attribute(nt, name) for name in ("pbr_base", "pbr_rme", "pbr_emit"))
    sep = nt.nodes.new("ShaderNodeSeparateXYZ")
    nt.links.new(rme.outputs["Vector"], sep.inputs["Vector"])
    nt.links.new(sep.outputs["X"], bsdf.inputs["Roughness"])
    nt.links.new(sep.outputs["Y"], bsdf.inputs["Metallic"])
    nt.links.new(sep.outputs["Z"], bsdf.inputs["Emission Strength"])
    nt.links.new(emit.outputs["Color"], bsdf.inputs["Emission Color"])
    return bsdf, base


def _attribute(nt, name: str, kind: str = "GEOMETRY"):
    node = nt.nodes.new("ShaderNodeAttribute")
    node.attribute_type = kind
    node.attribute_name = name
    return node


def _material(name: str, finish) -> bpy.types.Material:
    """The material `name`, made on first use only: the shared PBR nodes, then `finish(graph, bsdf,
    base)` links its base colour (and whatever else it adds)."""
    mat = bpy.data.materials.get(name)
    if mat is None:
        mat = bpy.data.materials.new(name)
        bsdf, base = _pbr_nodes(mat)
        finish(_Graph(mat.node_tree), bsdf, base)
    return mat


def _pbr_material() -> bpy.types.Material:
    """omnigen_pbr: plain parts; car paint (pattern car_paint) gets a clear coat, as the raster's
    car paint reflects the sky (its Fresnel-weighted coat)."""
    return _material(PBR, _plain_nodes)


def _plain_nodes(g: "_Graph", bsdf, base) -> None:
    g.nt.links.new(base.outputs["Color"], bsdf.inputs["Base Color"])
    kind = g.channels(_attribute(g.nt, "pbr_surface").outputs["Color"])[0]
    g.nt.links.new(g.equals(kind, PATTERNS["car_paint"]), bsdf.inputs["Coat Weight"])


class _Graph:
    """Arithmetic on a node tree's sockets, a Math, Mix or Map Range node an operation: how the
    raster shader's surface() (gl_raster) is written as Cycles shader nodes. Operands are sockets
    or numbers; an operation on numbers alone is done here, and one that cannot change its other
    operand (times 1, plus 0, a mix by 0) makes no node, so a material built for one pattern (its
    id and weights as numbers) holds only that pattern's terms, as the raster's per-pattern
    builds do (every node costs each shading point: one material for all patterns doubled a
    frame's time)."""

    def __init__(self, nt) -> None:
        self.nt = nt

    def _node(self, kind: str, inputs: dict, **props):
        node = self.nt.nodes.new(kind)
        for k, v in props.items():
            setattr(node, k, v)
        for key, v in inputs.items():
            if isinstance(v, (int, float)):
                node.inputs[key].default_value = float(v)
            elif isinstance(v, tuple):
                node.inputs[key].default_value = v
            else:
                self.nt.links.new(v, node.inputs[key])
        return node

    def math(self, op: str, a, b=0.0, c=0.0):
        return self._node("ShaderNodeMath", {0: a, 1: b, 2: c}, operation=op).outputs[0]

    def add(self, a, b):
        if _number(a) and _number(b):
            return a + b
        return b if a == 0.0 else a if b == 0.0 else self.math("ADD", a, b)

    def sub(self, a, b):
        if _number(a) and _number(b):
            return a - b
        return a if b == 0.0 else self.math("SUBTRACT", a, b)

    def mul(self, *factors):
        numbers = [float(f) for f in factors if _number(f)]
        k = float(np.prod(numbers)) if numbers else 1.0
        sockets = [f for f in factors if not _number(f)]
        if k == 0.0 or not sockets:
            return k
        out = sockets[0]
        for f in sockets[1:]:
            out = self.math("MULTIPLY", out, f)
        return out if k == 1.0 else self.math("MULTIPLY", out, k)

    def mix(self, a, b, t):
        """a + (b - a) t, t in [0, 1]."""
        if _number(t) and t in (0.0, 1.0):
            return a if t == 0.0 else b
        if _number(a) and _number(b):
            return a if a == b else self.add(a, self.mul(b - a, t))
        return self._node("ShaderNodeMix", {0: t, 2: a, 3: b}, data_type="FLOAT").outputs[0]

    def gain(self, amount, t):
        """1 + (amount - 1) t: a factor that is `amount` where t is 1 and 1 where it is 0."""
        return self.mix(1.0, amount, t)

    def smooth(self, a: float, b: float, x):
        """GLSL's smoothstep(a, b, x) (a > b too)."""
        if _number(x):
            u = min(max((x - a) / (b - a), 0.0), 1.0)
            return u * u * (3.0 - 2.0 * u)
        return self._node("ShaderNodeMapRange", {"Value": x, "From Min": a, "From Max": b},
                          interpolation_type="SMOOTHSTEP").outputs[0]

    def equals(self, x, value: float):
        """1 where x (a pattern id) is `value`, else 0."""
        return self.math("COMPARE", x, float(value), 0.5)

    def less(self, a, b):
        return float(a < b) if _number(a) and _number(b) else self.math("LESS_THAN", a, b)

    def greater(self, a, b):
        return float(a > b) if _number(a) and _number(b) else self.math("GREATER_THAN", a, b)

    def fract(self, x):
        return self.math("FRACT", x)

    def channels(self, color):
        sep = self._node("ShaderNodeSeparateColor", {0: color})
        return sep.outputs[0], sep.outputs[1], sep.outputs[2]

    def xyz(self, vector):
        sep = self._node("ShaderNodeSeparateXYZ", {0: vector})
        return sep.outputs[0], sep.outputs[1], sep.outputs[2]

    def image(self, image, u, v, interpolation: str = "Linear", extension: str = "REPEAT"):
        """(r, g) of `image` at (u, v) in texture coordinates."""
        vec = self._node("ShaderNodeCombineXYZ", {0: u, 1: v})
        tex = self._node("ShaderNodeTexImage", {"Vector": vec.outputs[0]}, image=image, interpolation=interpolation,
                         extension=extension)
        return self.channels(tex.outputs["Color"])[:2]

    def color_mix(self, a, b, t):
        if _number(t) and t in (0.0, 1.0):
            return a if t == 0.0 else b
        return self._node("ShaderNodeMix", {0: t, 6: a, 7: b}, data_type="RGBA").outputs[2]

    def color_scale(self, color, factor):
        """color times factor (a number, a float socket or a colour)."""
        if _number(factor) and factor == 1.0:
            return color
        if _number(factor):
            factor = (factor, factor, factor, 1.0)
        return self._node("ShaderNodeMix", {0: 1.0, 6: color, 7: factor}, data_type="RGBA", blend_type="MULTIPLY").outputs[2]


def _number(x) -> bool:
    return isinstance(x, (int, float))


SURFACE = "omnigen_surface"  # the surface materials: omnigen_surface_<pattern>, one a pattern
NOISE_IMAGE, WEAR_IMAGE = "omnigen_noise", "omnigen_road_wear"
SNOW_PROPERTY = "omnigen_snow_cover"  # the frame's snow cover, a scene property the surface materials read
GRANITE = (0.36, 0.355, 0.34)


def _surface_material(pattern: str) -> bpy.types.Material:
    """omnigen_surface_<pattern>: a procedural surface of materials.Surface as the raster shader
    draws it (gl_raster surface()), from world position and face normal alone: the noise table
    (materials.noise_table, the same one) in its octaves, tiles and joints, asphalt's resurfaced and
    worn stretches and the road-wear map (road_wear.py: oil, rubber, gutter grime), worn lane paint,
    kerb stones, dry grass, facades' storey bands, plinth and grime, roofs by building, yellower
    foliage, window panes with blinds. One material a pattern, its weights (SURFACE_WEIGHTS) built
    in; a face's scale, variant and spacing come from its pbr_surface attribute. Made once; the
    images it reads are made first (_surface_images), the wear map's placement in named Value nodes.

    Where it differs from the raster: joints and storey bands are drawn sharp (a path tracer
    averages them over a pixel's samples; the raster fades them by the pixel's footprint);
    reflections are Cycles' own; snow keeps materials.weathered's blend (no patches) and hides the
    pattern by the frame's snow cover."""
    return _material(f"{SURFACE}_{pattern}", lambda g, bsdf, base: _surface_nodes(g, bsdf, base, PATTERNS[pattern]))


def _surface_nodes(g: "_Graph", bsdf, base, kind: int) -> None:
    """A surface material's base colour: gl_raster's surface() for pattern `kind`."""
    nt = g.nt
    ax, ay, az, aw, cx, cy, cz = (float(w) for w in SURFACE_WEIGHTS[kind])
    is_ = {name: float(kind == PATTERNS[name]) for name in ("asphalt", "paint", "paving", "grass", "facade", "glass", "roof", "foliage")}
    geo = nt.nodes.new("ShaderNodeNewGeometry")
    px, py, pz = g.xyz(geo.outputs["Position"])
    nx, ny, nz = g.xyz(geo.outputs["Normal"])
    surface = _attribute(nt, "pbr_surface")
    _, scale, variant = g.channels(surface.outputs["Color"])
    spacing = surface.outputs["Alpha"]
    snow = _attribute(nt, SNOW_PROPERTY, "VIEW_LAYER").outputs["Fac"]
    up = g.greater(nz, 0.5)
    # the face's own coordinates: x, y on the ground, (along the face, z) on walls
    u = g.mix(g.sub(g.mul(py, nx), g.mul(px, ny)), px, up)
    v = g.mix(pz, py, up)
    noise = bpy.data.images[NOISE_IMAGE]
    cell = 1.0 / NOISE_SIZE
    lo = big = hi = fine = 0.5
    if ax or aw or is_["grass"] or is_["paint"]:
        lo, big = g.image(noise, g.mul(u, g.mix(0.8, 0.6, up), cell), g.mul(v, g.mix(0.06, 0.6, up), cell))
    if ay or az or is_["paint"] or is_["foliage"]:
        hi, fine = g.image(noise, g.mul(g.add(g.mul(u, 9.0), 31.7), cell), g.mul(g.add(g.mul(v, 9.0), 31.7), cell))
    lo, hi, fine = g.sub(lo, 0.5), g.sub(hi, 0.5), g.sub(fine, 0.5)
    m = g.mul(g.add(1.0, g.mul(2.0 * ax, lo)), g.add(1.0, g.mul(2.0 * ay, hi)), g.add(1.0, g.mul(2.0 * az, fine)))
    # asphalt and roofs: darker resurfaced stretches and lighter worn ones (the 20 m octave)
    if aw and (is_["asphalt"] or is_["roof"]):
        patches = g.mul(g.gain(0.55, g.smooth(0.56, 0.6, big)), g.gain(1.3, g.smooth(0.42, 0.22, big)))
        m = g.mul(m, g.gain(patches, aw))
    # roofs by building: a dark membrane (3 in 10); flat ones also gravel or a white membrane
    rv = g.fract(g.mul(variant, 7.31)) if is_["roof"] else 0.0
    m = g.mul(m, g.gain(0.45, g.mul(g.less(rv, 0.3), is_["roof"], up)))
    # tiles, kerb stones (1 m) and window panes: a value a cell, dark joints
    pane = 0.5
    if cx or cy or is_["glass"]:
        tile_u = g.mix(spacing if not is_["paving"] else 1.0, scale, up)
        tu, tv = g.math("DIVIDE", u, tile_u), g.math("DIVIDE", v, scale)
        pane = g.image(noise, g.mul(g.add(g.math("FLOOR", tu), g.add(g.mul(97.0, variant), 11.0)), cell),
                       g.mul(g.add(g.math("FLOOR", tv), 0.5), cell), "Closest")[0]
        if cy:
            fu, fv = g.fract(tu), g.fract(tv)
            eu = g.mul(g.math("MINIMUM", fu, g.sub(1.0, fu)), tile_u)
            ev = g.mul(g.math("MINIMUM", fv, g.sub(1.0, fv)), scale)
            joint = g.less(g.mix(eu, g.math("MINIMUM", eu, ev), up), cz)
            m = g.mul(m, g.sub(1.0, g.mul(cy, joint)))
        m = g.mul(m, g.add(1.0, g.mul(2.0 * cx, g.sub(pane, 0.5))))
    # facades: a band at each floor slab (lighter or darker by variant), a darker plinth, grime
    if is_["facade"]:
        facade = g.mul(g.sub(1.0, up), g.greater(nz, -0.5))
        band = g.less(g.mul(g.fract(g.math("DIVIDE", pz, scale)), scale), 0.32)
        storey = g.mul(g.gain(g.mix(1.22, 0.72, g.less(variant, 0.5)), band), g.mix(0.68, 1.0, g.smooth(0.7, 0.9, pz)),
                       g.add(0.8, g.mul(0.2, g.smooth(0.0, 2.5, pz))))
        m = g.mul(m, g.gain(storey, facade))
    if not _number(m):
        m = g.mix(m, 1.0, g.mul(snow, up))  # snow hides the pattern (its blend is in the base colour)
    albedo = g.color_scale(base.outputs["Color"], m)
    if is_["asphalt"]:  # what traffic leaves (road_wear.py's map, placed by the omnigen_wear_* values)
        x0, y0, sx, sy = (nt.nodes.new("ShaderNodeValue") for _ in range(4))
        for node, name in zip((x0, y0, sx, sy), ("x0", "y0", "sx", "sy")):
            node.name = f"omnigen_wear_{name}"
        stain, tracks = g.image(bpy.data.images[WEAR_IMAGE], g.mul(g.sub(px, x0.outputs[0]), sx.outputs[0]),
                                g.mul(g.sub(py, y0.outputs[0]), sy.outputs[0]), extension="EXTEND")
        wear = g.sub(g.add(g.mul(WEAR_STAIN, stain), g.mul(WEAR_RUBBER, tracks)), g.mul(WEAR_STAIN * WEAR_RUBBER, stain, tracks))
        albedo = g.color_scale(albedo, g.sub(1.0, g.mul(wear, g.sub(1.0, snow))))
    if is_["roof"]:
        flat_roof = g.mul(g.greater(nz, 0.98), g.sub(1.0, snow), g.greater(rv, 0.7))
        roof = g.color_scale(g.color_mix((0.34, 0.33, 0.31, 1.0), (0.62, 0.62, 0.6, 1.0), g.greater(rv, 0.8)), m)
        albedo = g.color_mix(albedo, roof, flat_roof)
    if is_["paving"]:  # kerb stones are granite, lighter than the paving
        albedo = g.color_mix(albedo, g.color_scale((*GRANITE, 1.0), m), g.mul(0.7, g.sub(1.0, up)))
    if is_["paint"]:  # road paint worn where wheels pass: asphalt shows through
        worn = g.smooth(0.5, 0.9, g.add(g.mul(0.55, g.add(lo, 0.5)), g.mul(0.45, g.add(hi, 0.5))))
        albedo = g.color_mix(albedo, (0.09, 0.09, 0.09, 1.0), g.mul(0.6, worn))
    if is_["grass"]:  # dry patches
        albedo = g.color_mix(albedo, g.color_scale((0.15, 0.13, 0.06, 1.0), m), g.mul(0.65, g.smooth(0.55, 0.8, big)))
    if is_["foliage"]:  # some clusters yellower
        albedo = g.color_mix(albedo, g.color_scale(albedo, (1.5, 1.25, 0.55, 1.0)), g.smooth(0.1, 0.3, hi))
    if is_["glass"]:  # most rooms dark behind the glass, a few panes with light blinds or curtains
        albedo = g.color_scale(albedo, g.add(0.15, g.mul(4.0, pane, pane, pane, pane, pane)))
    nt.links.new(albedo, bsdf.inputs["Base Color"])


def _surface_images(city) -> None:
    """The surface material's images, made once per scene build (never per frame) and packed into
    the .blend: the noise table (float, repeating) and the city's road-wear map (r stain, g wheel
    tracks; bytes, as road_wear_map makes it), placed over the city by the material's
    omnigen_wear_* values. Rebuilding a scene over another city replaces the map's pixels."""
    table = noise_table()
    rgba = np.zeros((*table.shape[:2], 4), dtype=np.float32)
    rgba[..., :2], rgba[..., 3] = table, 1.0
    _packed_image(NOISE_IMAGE, rgba, float_buffer=True)
    wear, (x0, y0, sx, sy) = road_wear_map(city)
    rgba = np.zeros((*wear.shape[:2], 4), dtype=np.float32)
    rgba[..., :2], rgba[..., 3] = wear / 255.0, 1.0
    _packed_image(WEAR_IMAGE, rgba, float_buffer=False)
    nodes = _surface_material("asphalt").node_tree.nodes
    for name, value in (("x0", x0), ("y0", y0), ("sx", sx), ("sy", sy)):
        nodes[f"omnigen_wear_{name}"].outputs[0].default_value = float(value)


def _packed_image(name: str, rgba: np.ndarray, float_buffer: bool) -> bpy.types.Image:
    """A (rows bottom-first, columns, 4) array as a packed, non-colour image named `name`."""
    h, w = rgba.shape[:2]
    img = bpy.data.images.get(name)
    if img is None:
        img = bpy.data.images.new(name, w, h, alpha=False, float_buffer=float_buffer)
    elif tuple(img.size) != (w, h):
        img.scale(w, h)  # in place: the material's texture nodes keep pointing at it
    img.colorspace_settings.name = "Non-Color"
    img.pixels.foreach_set(np.ascontiguousarray(rgba, dtype=np.float32).ravel())
    img.pack()
    return img


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


def _show(obj: bpy.types.Object, visible: bool) -> None:
    """Show or hide `obj` in renders; set only on a change (each set makes Blender rebuild its
    dependency graph's relations)."""
    if obj.hide_render == visible:
        obj.hide_render = not visible


FOG_CORNERS = np.array([[x, y, z] for z in (-1, 1) for y in (-1, 1) for x in (-1, 1)], dtype=np.float32)


def _fog_mesh() -> bpy.types.Mesh:
    """The fog box (sized per frame by _size_fog) with its volume material, made once."""
    mesh = bpy.data.meshes.new(FOG)
    faces = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    mesh.from_pydata(FOG_CORNERS.tolist(), [], faces)
    mat = bpy.data.materials.new(FOG)
    nt = mat.node_tree
    nt.nodes.clear()
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    vol = nt.nodes.new("ShaderNodeVolumePrincipled")
    vol.inputs["Color"].default_value = (0.85, 0.87, 0.9, 1.0)
    vol.inputs["Anisotropy"].default_value = 0.3
    nt.links.new(vol.outputs["Volume"], out.inputs["Volume"])
    mesh.materials.append(mat)
    return mesh


def _size_fog(obj: bpy.types.Object, density: float) -> None:
    """The fog box big enough that what lies beyond is fully extinct (transmittance < 1%), at most
    1.5 km, and its density (extinction, 1/m): values written into the box made once."""
    half = float(min(max(4.6 / density, 100.0), 1500.0))
    v = FOG_CORNERS * np.array([half, half, 150.0], dtype=np.float32) + np.array([0, 0, 148.0], dtype=np.float32)
    obj.data.vertices.foreach_set("co", v.ravel())
    obj.data.update()
    vol = next(n for n in obj.data.materials[0].node_tree.nodes if n.type == "PRINCIPLED_VOLUME")
    vol.inputs["Density"].default_value = float(density)


def _collection(name: str) -> bpy.types.Collection:
    col = bpy.data.collections.get(name)
    if col is None:
        col = bpy.data.collections.new(name)
        bpy.context.scene.collection.children.link(col)
    return col


TRIM_EVERY = 10
"""Frame updates between two _trim_heap calls (BlenderScene.update)."""


def _trim_heap() -> None:
    """Hand freed heap pages back to the system (glibc's malloc_trim), every TRIM_EVERY frame
    updates rather than every one: a trim took 37 ms of a downtown frame's update
    (bench_render.py --profile), and with a trim every tenth update resident memory still holds
    flat over a long run (+3.2% from frame 20 to 200: bench_render.py --memory-frames 200,
    rendering-speed.md)."""
    import ctypes

    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # not glibc
        pass


# ---------------------------------------------------------------------------------------------
# The scene
# ---------------------------------------------------------------------------------------------

FOG, PRECIPITATION = "omnigen_fog", "omnigen_precipitation"


def _slot_name(index: int) -> str:
    """An agent slot's name while it holds no agent (or between two names): never an agent's."""
    return f"omnigen_agent_slot_{index}"


class BlenderScene:
    """A bpy scene kept in step with a Scene: build once, `update` per frame, `save_blend`.

    Between frames only what changes is written, into datablocks made once: the static city's
    meshes are restyled in place (and only where a part's Material changed), agents fill a pool
    of objects (slot j holds the frame's j-th agent: its mesh rewritten in place, its transform,
    name, ids; slots past the frame's agents hidden), the street lamps, fog box and precipitation
    are made once and shown, hidden or rewritten, the sky and sun take new values. Nothing is
    deleted, which is what a frame cost before: Blender's object removal scans every datablock
    (2 to 4 s a frame over downtown's 850 objects).

    A frame is what a fresh process rendering only that frame makes, byte for byte: the objects
    are linked in the order a new build links them (static city, agents, sun, lamps, fog,
    precipitation; hidden ones are not rendered), and `update` frees Cycles' persistent session,
    whose object and light arrays otherwise keep the order of earlier frames (Cycles appends new
    objects and fills a removed one's place with the last), which changes which light a random
    number picks. The renders of one frame (beauty, labels, a redrawn camera) still share it.
    Where an update's time goes: `benchmarks/bench_render.py --profile --no-raster`."""

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
        self.objects: dict[str, RenderObject] = {}
        self.focus = (0.0, 0.0, 0.0)
        self.scene = scene
        self._buildings = {b.building_id: b for b in scene.city.buildings}
        self._static: dict[str, _Painted] = {}
        self._slots: list[bpy.types.Object] = []  # slot j shows the frame's j-th agent
        self._held: list[_Painted | None] = []  # the mesh each slot shows (None: hidden, the empty mesh)
        self._agent_meshes = _AgentMeshes()
        self._no_agent: bpy.types.Mesh | None = None  # the empty mesh a hidden slot shows
        self._film = None  # the last beauty render's develop (render), for save_blend's exposure
        self._updates = 0  # frame updates so far (TRIM_EVERY)
        self._agent_looks: dict[tuple[str, ...], tuple] = {}  # roles -> surfaces and their _looks (_agent_surfaces)
        self._slot_labels: dict[int, tuple] = {}  # slot -> (instance id, category, dims) as written (_label_slot)
        for name in (STATIC, AGENTS, WEATHER):  # link order is render order: made first, in this order
            _collection(name)
        _surface_images(scene.city)
        objects = compile_scene(scene)
        for obj in objects:
            if obj.kind != "agent":
                self._add_static(obj)
        self._place_agents([obj for obj in objects if obj.kind == "agent"])
        self.objects = {obj.name: obj for obj in objects}
        self._environment_objects(scene)
        self._environment(scene)

    # -- objects ----------------------------------------------------------------------------

    def _surfaces(self, obj: RenderObject) -> dict[str, Surface]:
        building = self._buildings.get(obj.name) if obj.kind == "building" else None
        return {role: part_surface(obj.kind, role, self.scene.city, building) for role in obj.parts}

    def _agent_surfaces(self, obj: RenderObject) -> tuple[dict[str, Surface], tuple]:
        """An agent's surfaces and their _looks, which follow its roles alone
        (materials.agent_surface): made once per set of roles, not for each of a frame's hundreds
        of agents (read, never changed)."""
        roles = tuple(obj.parts)
        kept = self._agent_looks.get(roles)
        if kept is None:
            surfaces = self._surfaces(obj)
            kept = self._agent_looks[roles] = (surfaces, _looks(surfaces))
        return kept

    def _add_static(self, obj: RenderObject) -> None:
        painted = _paint_mesh(bpy.data.meshes.new(obj.name), obj.parts, self._surfaces(obj))
        painted.paint(obj.materials)
        bobj = bpy.data.objects.new(obj.name, painted.mesh)
        bobj.matrix_world = _matrix(obj.matrix_world)
        bobj["omnigen_kind"] = obj.kind
        _collection(STATIC).objects.link(bobj)
        self._static[obj.name] = painted

    def _place_agents(self, agents: list[RenderObject]) -> None:
        """Slot j takes agent j: a mesh of its shape (_AgentMeshes), moved to its vertices when it
        holds other parts (the asset cache returns the same parts for the same asset and dims), its
        colours where they differ, its transform, ids and name; slots past the last agent are
        hidden and show the empty mesh."""
        # None: the slot's mesh holds these very parts (the same asset and dims), lent back to it unchanged
        stacked = [None if j < len(self._held) and self._held[j] is not None and self._held[j].parts is obj.parts
                   else _stack_parts(obj.parts) for j, obj in enumerate(agents)]
        surfaces, looks = zip(*(self._agent_surfaces(obj) for obj in agents)) if agents else ((), ())
        shapes = [self._held[j].shape if st is None else _shape(*st, looks[j]) for j, st in enumerate(stacked)]
        lent = self._agent_meshes.lend(shapes, self._held)
        for j, obj in enumerate(agents):
            if j == len(self._slots):
                bobj = bpy.data.objects.new(_slot_name(j), self._empty_mesh())
                _collection(AGENTS).objects.link(bobj)
                self._slots.append(bobj)
                self._held.append(None)
            bobj, painted = self._slots[j], lent[j]
            if painted is None:  # a shape no kept mesh is free for (never a slot lent back its own parts)
                painted = _build_mesh(self._agent_meshes.fresh(_slot_name(j)), *stacked[j], surfaces[j])
                painted.shape, painted.parts = shapes[j], obj.parts
                self._agent_meshes.keep(painted)
            elif painted.parts is not obj.parts:
                _set_positions(painted.mesh, stacked[j][0])
                painted.parts = obj.parts
                self._agent_meshes.moved += 1
            painted.paint(obj.materials)
            if self._held[j] is not painted:  # else the slot shows this mesh already
                bobj.data = painted.mesh
            self._held[j] = painted
            bobj.matrix_world = _matrix(obj.matrix_world)
            self._label_slot(j, int(obj.instance_id), obj.category, tuple(float(d) for d in obj.dims))
            _show(bobj, True)
        for j in range(len(agents), len(self._slots)):
            bobj = self._slots[j]
            _show(bobj, False)
            if self._held[j] is not None:
                bobj.data = self._empty_mesh()
                self._held[j] = None
            self._label_slot(j, 0)
        self._name_slots([obj.name for obj in agents])

    def _label_slot(self, j: int, instance_id: int, category: str | None = None,
                    dims: tuple[float, ...] | None = None) -> None:
        """Slot j's object index (the label pass reads it) and the properties a saved .blend
        shows (instance id, category, dims, kind), each written only when it changed: a slot
        keeps its index from frame to frame (in a frame drawn alone, agent j has instance id
        j + 1) and often its category, and each write is a property lookup in Blender (None: left
        as it is, a hidden slot's)."""
        bobj, last = self._slots[j], self._slot_labels.get(j)
        if last is None:
            bobj["omnigen_kind"] = "agent"
            last = (None, None, None)
        if instance_id != last[0]:
            bobj.pass_index = instance_id
            bobj["omnigen_instance_id"] = instance_id
        if category is not None and category != last[1]:
            bobj["omnigen_category"] = category
        if dims is not None and dims != last[2]:
            bobj["omnigen_dims"] = list(dims)
        self._slot_labels[j] = (instance_id, last[1] if category is None else category,
                                last[2] if dims is None else dims)

    def _empty_mesh(self) -> bpy.types.Mesh:
        if self._no_agent is None:
            self._no_agent = bpy.data.meshes.new("omnigen_agent_none")
        return self._no_agent

    def _name_slots(self, names: list[str]) -> None:
        """Each used slot named as its agent (Cycles seeds an object's random number from its
        name), the others by their index; a slot renamed goes through its own index name first,
        so no agent's name is ever taken by another slot (Blender would add a suffix)."""
        wanted = names + [_slot_name(j) for j in range(len(names), len(self._slots))]
        moved = [j for j, bobj in enumerate(self._slots) if bobj.name != wanted[j]]
        for j in moved:
            self._slots[j].name = _slot_name(j)
        for j in moved:
            self._slots[j].name = wanted[j]

    def update(self, scene: Scene) -> None:
        """Next frame over the same city: the agents, the static city's colours, the environment."""
        if scene.city is not self.scene.city and scene.city != self.scene.city:
            raise ValueError("BlenderScene.update needs the same city; build a new BlenderScene for another")
        objects = compile_scene(scene)
        self.scene = scene
        self._place_agents([obj for obj in objects if obj.kind == "agent"])
        for obj in objects:
            if obj.kind != "agent":
                self._static[obj.name].paint(obj.materials)
        self.objects = {obj.name: obj for obj in objects}
        self._environment(scene)
        self._fresh_session()
        self._updates += 1
        if self._updates % TRIM_EVERY == 0:
            _trim_heap()

    def _fresh_session(self) -> None:
        """Free Cycles' persistent session (switching persistent data off frees it), so the frame's
        first render syncs the scene as a new process's first render does. Measured over downtown
        at 96 x 64: no more CPU time than keeping it, since every frame changes the agents, the
        colours of the whole city and the sky that the kept session would re-sync anyway."""
        render = self.bscene.render
        render.use_persistent_data = False
        render.use_persistent_data = True

    # -- environment ------------------------------------------------------------------------

    def _environment_objects(self, scene: Scene) -> None:
        """The sun, every street lamp (shown when the lamps are on), the fog box and the
        precipitation, made once in the order a frame links them, so a frame's lights keep their
        order whatever frames came before."""
        self._sun_lamp = bpy.data.objects.new("omnigen_sun", bpy.data.lights.new("omnigen_sun", "SUN"))
        _collection(WEATHER).objects.link(self._sun_lamp)
        lit = replace(scene, lighting=replace(scene.lighting, street_lights_on=True))
        self._lamps = []
        for lamp in lamp_lights(lit):
            data = bpy.data.lights.new(lamp.name, "SPOT")
            data.energy = lamp.power
            data.color = lamp.color
            data.spot_size = lamp.spot_angle
            data.shadow_soft_size = 0.2
            obj = bpy.data.objects.new(lamp.name, data)
            obj.location = lamp.position  # spots shine along -z: straight down
            obj["omnigen_lamp"] = True
            _collection(WEATHER).objects.link(obj)
            self._lamps.append(obj)
        self._fog = self._weather_object(FOG, "fog", _fog_mesh()) if self.volumes else None
        mesh = bpy.data.meshes.new(PRECIPITATION)
        self._precip = self._weather_object(PRECIPITATION, "rain", mesh) if self.precipitation else None

    def _weather_object(self, name: str, role: str, mesh: bpy.types.Mesh) -> bpy.types.Object:
        obj = bpy.data.objects.new(name, mesh)
        obj["omnigen_weather"] = role
        obj["omnigen_follow"] = True
        obj.hide_render = True
        _collection(WEATHER).objects.link(obj)
        return obj

    def _environment(self, scene: Scene) -> None:
        self.bscene[SNOW_PROPERTY] = float(scene.weather.snow_cover)  # the surface material reads it
        self._sky(scene)
        self._sun(scene)
        for obj in self._lamps:
            _show(obj, scene.lighting.street_lights_on)
        self._weather(scene)

    def _sky(self, scene: Scene) -> None:
        """The physical sky (MULTIPLE_SCATTERING, its sun disc dark: the sun lamp is the sun; the disc
        lit the city a second time, ten times over on a clear day) mixed towards an even grey by cloud
        cover, both scaled to a horizontal irradiance of one (sky_irradiance) and then set to the
        frame's skylight (daylight: the raster's share of the daylight), so the sky lights the
        scene as the raster's does and the exposure knows the light. Camera rays see it
        CAMERA_SKY_GAIN times brighter."""
        light, w = scene.lighting, scene.weather
        world = bpy.data.worlds.get("omnigen_world") or bpy.data.worlds.new("omnigen_world")
        self.bscene.world = world
        nt = world.node_tree
        if "omnigen_sky_strength" not in nt.nodes:
            nt.nodes.clear()
            out = nt.nodes.new("ShaderNodeOutputWorld")
            bg = nt.nodes.new("ShaderNodeBackground")
            sky = nt.nodes.new("ShaderNodeTexSky")
            sky.name = "omnigen_sky"
            sky.sky_type = "MULTIPLE_SCATTERING"
            # No second sun: the disc gives no light (the lamp is the sun). Kept on at intensity 0:
            # without the disc Cycles took 2.5-3.5 s more to set up each frame's sky (2 cores).
            sky.sun_disc, sky.sun_intensity = True, 0.0
            g = _Graph(nt)
            unit = g._node("ShaderNodeMix", {0: 1.0, 6: sky.outputs["Color"]}, data_type="RGBA", blend_type="MULTIPLY")
            unit.name = "omnigen_sky_unit"
            grey = np.array([1.0, 1.02, 1.06]) / (math.pi * _luminance((1.0, 1.02, 1.06)))  # an even sky of irradiance one
            mix = g._node("ShaderNodeMix", {6: unit.outputs[2], 7: (*grey, 1.0)}, data_type="RGBA")
            mix.name = "omnigen_clouds"
            camera = nt.nodes.new("ShaderNodeLightPath").outputs["Is Camera Ray"]
            strength = g._node("ShaderNodeMath", {0: camera}, operation="MULTIPLY_ADD")
            strength.name = "omnigen_sky_strength"
            nt.links.new(mix.outputs[2], bg.inputs["Color"])
            nt.links.new(strength.outputs[0], bg.inputs["Strength"])
            nt.links.new(bg.outputs["Background"], out.inputs["Surface"])
        elevation, aerosol = max(light.sun_elevation, -5.0), 1.0 + 4.0 * min(w.fog_density / 0.01, 1.0)
        sky = nt.nodes["omnigen_sky"]
        sky.sun_elevation = math.radians(elevation)
        sky.sun_rotation = sun_rotation_for_azimuth(light.sun_azimuth)
        sky.aerosol_density = aerosol
        k = 1.0 / sky_irradiance(elevation, aerosol)
        nt.nodes["omnigen_sky_unit"].inputs[7].default_value = (k, k, k, 1.0)
        nt.nodes["omnigen_clouds"].inputs[0].default_value = float(w.cloud_cover)
        e_sky = daylight(scene)[1]
        strength = nt.nodes["omnigen_sky_strength"]
        strength.inputs[1].default_value = (CAMERA_SKY_GAIN - 1.0) * e_sky
        strength.inputs[2].default_value = e_sky

    def _sun(self, scene: Scene) -> None:
        light, w = scene.lighting, scene.weather
        obj = self._sun_lamp
        d = np.asarray(light.sun_direction)
        obj.matrix_world = _matrix(_look_along(-d))
        obj.data.energy = float(light.sun_strength) if light.sun_elevation > 0 else 0.0
        obj.data.angle = math.radians(0.53 + 25.0 * float(w.cloud_cover))
        obj.data.color = _sun_color(light.sun_elevation)

    def _weather(self, scene: Scene) -> None:
        w = scene.weather
        if self._fog is not None:
            _show(self._fog, w.fog_density > 0)
            if w.fog_density > 0:
                _size_fog(self._fog, w.fog_density)
        if self._precip is not None:
            falls = w.precipitation > 0 and w.kind in ("rain", "snow")
            _show(self._precip, falls)
            if falls:
                self._precip_mesh(scene)
        self.place_weather(self.focus)

    def _precip_mesh(self, scene: Scene) -> None:
        """The precipitation's triangles for this frame, into the one precipitation mesh."""
        w = scene.weather
        rng = instant_extra_rng(scene.dataset_seed, scene.frame_index, scene.instant)  # frame_streams' "extra" at instant 0
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
        mesh = self._precip.data
        _set_triangles(mesh, np.asarray(v, dtype=np.float32), np.asarray(f, dtype=np.int32))
        _set_materials(mesh, [mat])
        self._precip["omnigen_weather"] = w.kind

    def place_weather(self, focus) -> None:
        """Centre the fog box and the precipitation on `focus` (x, y, z): the camera, usually."""
        self.focus = tuple(float(c) for c in focus)
        for obj in (self._fog, self._precip):
            if obj is not None:
                z = 0.0 if obj is self._fog else max(self.focus[2] - WEATHER_BOX[2] / 2, 0.0)
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
        # beauty: Image -> a linear float EXR, which render() exposes and encodes (expose)
        ng = bpy.data.node_groups.new("omnigen_beauty", "CompositorNodeTree")
        rl = ng.nodes.new("CompositorNodeRLayers")
        fo = ng.nodes.new("CompositorNodeOutputFile")
        fo.format.media_type = "IMAGE"
        fo.format.file_format = "OPEN_EXR"
        fo.format.color_mode = "RGB"
        fo.format.color_depth = "32"
        fo.format.exr_codec = "NONE"
        item = fo.file_output_items.new("RGBA", "rgb")
        item.save_as_render = False
        ng.links.new(rl.outputs["Image"], fo.inputs["rgb"])
        fo.file_output_items.new("FLOAT", "depth")  # where the road is: what the exposure meters (road_pixels)
        ng.links.new(rl.outputs["Depth"], fo.inputs["depth"])
        # A user's own render of a saved .blend: the Standard view transform at the frame's exposure
        # (render() sets it), close to what omnigen wrote but for the tone curve.
        sc.view_settings.view_transform, sc.view_settings.look = "Standard", "None"
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

    def render(self, camera: Camera, labels: bool = True, develop: bool = True) -> dict:
        """Cycles RGB (uint8, exposed and encoded as the raster's camera does: expose) plus the label
        pass's depth (camera z, inf where nothing was hit) and instance ids (None with
        labels=False: the caller draws them another way); `seconds` is the beauty render's time,
        `gain` the exposure applied to Cycles' linear radiance. With develop=False, "rgb" and
        "gain" are None and "develop" makes them (a function of the beauty render's arrays
        alone): the caller develops the image where it costs least (rigs/render.py, on the
        writer's thread while the next frame is set up)."""
        self._set_camera(camera)
        self.place_weather(tuple(float(v) for v in camera.center))
        self._apply_quality()
        fog = self._fog
        skip_fog = fog is not None and not fog.hide_render and self.scene.weather.fog_density < self.quality["min_volume_density"]
        if skip_fog:
            fog.hide_render = True
        t0 = time.perf_counter()
        try:
            self._run(self._beauty_tree)
            seconds = time.perf_counter() - t0
            film = _once(partial(develop_frame, _read_exr_rgb(self._single("beauty_", "rgb")),
                                 _read_exr_channel(self._single("beauty_", "depth")), camera, self.scene))
            self._film = film
            # The label pass runs before the fog comes back: with the same objects visible as in
            # the beauty render, Cycles (persistent data) reuses the beauty render's BVH instead
            # of building the city's again (about 2 s at 640 x 640 on the 2-core machine).
            depth, instance = self._labels(None) if labels else (None, None)
        finally:
            if skip_fog:
                fog.hide_render = False
        rgb = gain = None
        if develop:
            rgb, gain = film()
            self.bscene.view_settings.exposure = float(math.log2(gain))
        return {"rgb": rgb, "depth": depth, "instance": instance, "seconds": seconds, "gain": gain, "develop": film}

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
        depth, index = (_read_exr_channel(self._single("labels_", name)) for name in ("depth", "index"))
        depth[depth >= 1e9] = np.inf
        return depth, np.rint(index).astype(np.uint16)

    # -- inspection and output ----------------------------------------------------------------

    def objects_summary(self) -> list[dict]:
        """Name, instance id, class and world box of every scene object, read back from bpy."""
        out = []
        for col in (STATIC, AGENTS):
            for bobj in _collection(col).objects:
                if bobj.hide_render:
                    continue  # an agent slot that holds no agent this frame
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
        """Sun, lamps, fog and precipitation shown this frame: name, role and location (for checks and tools)."""
        out = []
        for obj in _collection(WEATHER).objects:
            if obj.hide_render:
                continue  # lamps by day, no fog, no rain: made once, hidden
            role = "lamp" if obj.get("omnigen_lamp") else obj.get("omnigen_weather", "sun" if obj.name == "omnigen_sun" else "")
            out.append({"name": obj.name, "role": role, "location": tuple(obj.location)})
        return out

    def agent_mesh_counts(self) -> dict[str, int]:
        """Agent meshes built (new shapes) and moved (another agent's vertices in a kept mesh) so far."""
        return {"built": self._agent_meshes.built, "moved": self._agent_meshes.moved}

    def datablock_counts(self) -> dict[str, int]:
        """How many meshes, objects, lights and materials exist: flat across frames, or a leak."""
        return {"meshes": len(bpy.data.meshes), "objects": len(bpy.data.objects), "lights": len(bpy.data.lights),
                "materials": len(bpy.data.materials), "images": len(bpy.data.images)}

    def save_blend(self, path: str | Path) -> Path:
        """Write the scene as a .blend a user opens in Blender (relative paths, compressed), at the
        exposure of the last rendered frame (its develop, run here only if its writer has not yet)."""
        if self._film is not None:
            self.bscene.view_settings.exposure = float(math.log2(self._film()[1]))
        path = Path(path).resolve()
        path.parent.mkdir(parents=True, exist_ok=True)
        bpy.ops.wm.save_as_mainfile(filepath=str(path), check_existing=False, compress=True, copy=True)
        return path


def _once(make):
    """`make()` run once, by whichever thread asks first (the writer, or save_blend for the
    exposure); every later call returns that result."""
    import threading

    lock, made = threading.Lock(), []

    def get():
        with lock:
            if not made:
                made.append(make())
            return made[0]

    return get


def _read_exr_rgb(path: str) -> np.ndarray:
    """(H, W, 3) float32 of an RGB EXR, top row first (as Blender's File Output writes it)."""
    import OpenEXR

    with OpenEXR.File(path, separate_channels=True) as f:
        ch = f.channels()
        return np.stack([np.asarray(ch[c].pixels, dtype=np.float32) for c in "RGB"], axis=-1)


def _read_exr_channel(path: str) -> np.ndarray:
    """(H, W) float32 of a one-channel EXR (R, V or whichever it has)."""
    import OpenEXR

    with OpenEXR.File(path, separate_channels=True) as f:
        ch = f.channels()
        key = "R" if "R" in ch else ("V" if "V" in ch else next(iter(ch)))
        return np.asarray(ch[key].pixels, dtype=np.float32).copy()


def sun_rotation_for_azimuth(azimuth_deg: float) -> float:
    """Sky Texture's sun_rotation (radians) for an azimuth clockwise from north (+y) to east (+x).

    Measured on bpy 5.0.1 (an equirectangular render of the sky): rotation 0 puts the sun at +y,
    90 degrees at +x, so the two agree. test_scene_blender.py renders the sky to keep it so.
    """
    return float(math.radians(azimuth_deg)) % (2 * math.pi)


def _matrix(m: np.ndarray) -> mathutils.Matrix:
    """A 4x4 numpy matrix (rows) as Blender's Matrix. Assigning nested lists to matrix_world
    would be read column by column, i.e. transposed."""
    return mathutils.Matrix(np.asarray(m, dtype=np.float64).tolist())  # tolist: the same Python floats, made in C


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
