"""A minimal OpenGL 3.3 core rasteriser for the raster preview: a handful of draw calls a frame.

Why not pyrender's renderer: on software GL (Mesa llvmpipe) a frame's cost was Python work per
draw call (pyrender binds every uniform, light and material per primitive: ~0.35 ms a call,
~870 calls a colour pass) plus a multisampled segmentation pass and framebuffer reads nobody
used. Here the geometry is uploaded as two indexed vertex buffers (the static city, once; this
frame's agents) whose vertices carry a material slot, a surface pattern and an instance id;
materials live in a small float texture, so restyling the city for the frame's weather is one
texture upload and each pass is one or two draw calls:
- sun shadow map (when the sun casts shadows): depth only, from the sun, orthographic;
- colour: 4x multisampled, pyrender's metallic-roughness shading (one directional sun, emission,
  encoded with the sRGB transfer function and the camera's tone curve, TONE_CONTRAST) with procedural surfaces (on asphalt the city's
  road-wear map, set_road_wear: traffic's oil, rubber and grime; snow in patches, cleared off the
  wheel tracks, in the SNOW build), the shadow lookup, a sky/ground
  hemisphere light (the sky's part scaled by the city's sky-view map, set_sky_view), lamps at night (a second build of the shader) and the exposure (see Light);
  fog over the ray length and the sky gradient (raster_backend's atmosphere) are applied here
  too, per fragment; then the camera's automatic exposure on the read-back frame (auto_exposure);
- ids and depth: not multisampled, an unsigned-integer target, so ids are exact (never averaged at
  edges) and each pixel's depth belongs to the object its id names; the look never touches it;
- ids of chosen agents alone (silhouettes): the agents' index ranges drawn with one
  glMultiDrawElements, nothing else.

The context comes from pyrender's EGL platform (headless; llvmpipe needs no GPU). Camera: the
passes take a world -> clip matrix, omnigen.camera.Camera's gl_projection(ZNEAR, ZFAR) @ gl_view():
pyrender's IntrinsicsCamera matrix given cx + 0.5, cy + 0.5 (pixel centres at integers,
conventions.md), so pixels land exactly where they did with pyrender.
"""

from __future__ import annotations

import ctypes
import os
from collections.abc import Callable
from dataclasses import dataclass, field

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402
from OpenGL import GL as gl  # noqa: E402

from omnigen.scenes.materials import NOISE_SIZE, SNOW, SNOW_BLEND, SURFACE_WEIGHTS, noise_table  # noqa: E402
from omnigen.scenes.road_wear import WEAR_CLEARED, WEAR_RUBBER, WEAR_STAIN  # noqa: E402

ZNEAR, ZFAR = 0.25, 3000.0
MSAA_SAMPLES = 4
SLOTS_PER_ROW = 1024  # material texture: slot s at (s % 1024, 2 * (s // 1024)) and the row below
AGENT_KINDS = -1  # the colour shader's build for agents (their parts are plain or car paint)
MAX_LAMPS = 16  # street lamps lighting a frame (the nearest to the view)
SHADOW_SIZE = 1024  # the sun's shadow map, texels a side
AE_TARGET = 0.18  # auto exposure: the frame's mean linear luminance it aims at (18% grey)
AE_STRIDE = 4  # it meters every 4th pixel of every 4th row (a camera meters a coarse grid)
# What traffic leaves on asphalt: road_wear.WEAR_STAIN, WEAR_RUBBER and WEAR_CLEARED (shared with Cycles).
# A lane's bands run along it, and a camera sees the road at a grazing angle: a pixel's footprint is
# long along the view and narrow across it, so the map is filtered anisotropically (wear() in the
# shader: as many lookups as the footprint is longer than wide, WEAR_TAPS at most, along its long
# axis, each at the mip level of its short axis) instead of averaging the bands away across the
# lane. Not the texture's own anisotropic filter: llvmpipe's (Mesa 22.3) took 4 minutes for one
# 640 x 640 dashcam frame of a street lined with parked cars (the asphalt draw alone; 0.13 s here).
WEAR_TAPS = 4

# The output encoding: the sRGB transfer function (IEC 61966-2-1; its linear toe keeps shadows
# darker than a plain 2.2 power), as the PNGs are read, then the camera's tone curve (below);
# _SRGB_GLSL is the same in the shaders (encode()).
TONE_CONTRAST = 0.5
"""The camera's tone curve on the sRGB-encoded value v: v + TONE_CONTRAST * (smoothstep(v) - v).

Why: a camera's image processor does not stop at the sRGB transfer function; its tone curve is an
S, steeper in the mid-tones than at the ends (1.25x at mid-grey here, 0.5x at black and white), so
real frames hold more contrast than a plain encoding of the same light (KITTI's median luminance
std 77 against 54-60 for pole and ego frames without it). The value was chosen on the benchmark's
renders of the four presets: with it every rig's luminance histogram is closer to KITTI's by
intersection than without it (benchmarks/bench_realism.py; docs/realism.md). It is monotone for
TONE_CONTRAST < 1, so the automatic exposure inverts it exactly (decode)."""
_SRGB_GLSL = """
vec3 srgb(vec3 c) {
    c = clamp(c, 0.0, 1.0);
    return mix(12.92 * c, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(0.0031308, c));
}
vec3 encode(vec3 c) {
    vec3 v = srgb(c);
    return mix(v, v * v * (3.0 - 2.0 * v), %TONE%);
}
""".replace("%TONE%", repr(float(TONE_CONTRAST)))


def srgb_encode(c: np.ndarray) -> np.ndarray:
    """Linear [0, 1] -> sRGB-encoded [0, 1] (the shaders' srgb())."""
    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1.0 / 2.4) - 0.055)


def srgb_decode(v: np.ndarray) -> np.ndarray:
    """sRGB-encoded [0, 1] -> linear."""
    v = np.asarray(v, dtype=np.float64)
    return np.where(v <= 0.04045, v / 12.92, np.power((v + 0.055) / 1.055, 2.4))


def tone(v: np.ndarray) -> np.ndarray:
    """The camera's tone curve (TONE_CONTRAST) on sRGB-encoded values in [0, 1]."""
    v = np.clip(np.asarray(v, dtype=np.float64), 0.0, 1.0)
    return v + TONE_CONTRAST * (v * v * (3.0 - 2.0 * v) - v)


_TONE_GRID = np.linspace(0.0, 1.0, 4097)


def untone(v: np.ndarray) -> np.ndarray:
    """The tone curve's inverse (tabulated; the curve is monotone)."""
    return np.interp(np.asarray(v, dtype=np.float64), tone(_TONE_GRID), _TONE_GRID)


def encode(c: np.ndarray) -> np.ndarray:
    """Linear [0, 1] -> the frame's code value in [0, 1]: sRGB, then the tone curve (the shaders' encode())."""
    return tone(srgb_encode(c))


def decode(v: np.ndarray) -> np.ndarray:
    """A frame's code value in [0, 1] -> linear (encode's inverse)."""
    return srgb_decode(untone(v))


_LINEAR = decode(np.arange(256) / 255.0)  # 8-bit code -> linear


def auto_exposure(rgb: np.ndarray, max_gain: float, target: float = AE_TARGET) -> np.ndarray:
    """A camera's automatic exposure on a finished frame: the gain g in [1, max_gain] that brings
    the mean linear luminance of the metered pixels (saturated ones count as 1, as a sensor's
    do) up to `target`, applied in linear light (one 256-entry table).

    Why only up: the daylight exposure (raster_backend.illumination) already puts a white sunlit
    face at the clip, so a frame whose mean is under 18% grey is one that is mostly in shade or
    dark stuff (a street in a tower's shadow, an overcast canyon): a camera opens up for it. A
    frame at or above the target (bright sky, snow) keeps its exposure, so nothing the frame
    shows bright is lost; what was saturated stays saturated. Deterministic: numpy on the frame.
    """
    if max_gain <= 1.0:
        return rgb
    y = (_LINEAR[rgb[::AE_STRIDE, ::AE_STRIDE]] @ np.array([0.2126, 0.7152, 0.0722])).ravel()
    if y.size == 0 or y.mean() >= target:
        return rgb
    lo, hi = 1.0, float(max_gain)
    if np.minimum(y * hi, 1.0).mean() > target:
        for _ in range(24):  # the mean of min(g y, 1) grows with g: bisect
            g = 0.5 * (lo + hi)
            if np.minimum(y * g, 1.0).mean() > target:
                hi = g
            else:
                lo = g
    lut = np.round(255.0 * encode(hi * _LINEAR)).astype(np.uint8)
    return lut[rgb]

_COLOR_VS = """#version 330 core
layout(location = 0) in vec3 position;
layout(location = 2) in float slot;
layout(location = 4) in vec4 surface_row;
layout(location = 5) in vec4 surface_amp;
layout(location = 6) in vec4 surface_cell;
uniform mat4 VP;
uniform mat4 shadow_matrix;
uniform sampler2D materials;
out vec3 shadow_coord;  // affine in the position: exact when interpolated
out vec3 frag_position;
flat out vec4 base_metal;
flat out vec4 emis_rough;
flat out vec4 pattern;
flat out vec4 amp;
flat out vec3 cell_w;
void main() {
    gl_Position = VP * vec4(position, 1.0);
    frag_position = position;
    shadow_coord = (shadow_matrix * vec4(position, 1.0)).xyz;
    int s = int(slot + 0.5);
    ivec2 c = ivec2(s % %SLOTS%, 2 * (s / %SLOTS%));
    base_metal = texelFetch(materials, c, 0);
    emis_rough = texelFetch(materials, c + ivec2(0, 1), 0);
    pattern = surface_row;
    amp = surface_amp;
    cell_w = surface_cell.xyz;
}
""".replace("%SLOTS%", str(SLOTS_PER_ROW))

# Procedural surfaces: pure functions of the world position (and the face's normal), so a surface
# looks the same from every camera and every frame. The noise is value noise: a 256 x 256 table of
# random values (computed at start-up from a fixed seed, nothing downloaded) sampled with bilinear
# filtering as a repeating texture; one texel is one noise cell, so N(p * f) is noise with f cells
# a metre. Its mipmaps average the noise where a pixel spans many cells (no shimmering grain at a
# distance). Joints (tiles, kerbs) and storey bands are antialiased with the pixel's footprint `fp`
# (metres, from fwidth).
#
# Written branch-free on purpose: llvmpipe runs both sides of an `if` under a mask, so a shader
# with a branch per pattern pays for every pattern at every pixel. Instead every pixel takes the
# same four noise octaves (two fetches) and one value per tile cell, and a pattern is a row of
# weights (SURFACE_WEIGHTS, per vertex: indexing a constant array per pixel is a chain of selects
# on llvmpipe) plus a few masked terms.
# Per pattern: materials.SURFACE_WEIGHTS, shared with Cycles' surface material.


def surface_attributes(rows: np.ndarray) -> np.ndarray:
    """(N, 4) surface rows (materials.Surface.row) -> (N, 12) vertex attributes: the row, then its
    pattern's weights (SURFACE_WEIGHTS) padded to two vec4s."""
    rows = np.asarray(rows, dtype=np.float32).reshape(-1, 4)
    out = np.zeros((len(rows), 12), dtype=np.float32)
    out[:, :4] = rows
    out[:, 4:11] = SURFACE_WEIGHTS[rows[:, 0].astype(np.int64)]
    return out


def _kind_defines(kind: int) -> str:
    """A pattern's build: its number and its weights as constants (the compiler then drops the
    noise octaves and joints a pattern does not use: plain parts fetch no noise at all)."""
    w = [f"{float(x):.6f}" for x in SURFACE_WEIGHTS[kind]]
    return (f"#define KIND {int(kind)}\n#define SURFACE_AMP vec4({w[0]}, {w[1]}, {w[2]}, {w[3]})\n"
            f"#define SURFACE_CELL vec3({w[4]}, {w[5]}, {w[6]})\n")


_SURFACES_GLSL = """
const float WEAR_STAIN = %WEAR_STAIN%;
const float WEAR_RUBBER = %WEAR_RUBBER%;
const float WEAR_CLEARED = %WEAR_CLEARED%;
vec2 wear(vec2 xy) {  // the road-wear map at xy, filtered over the pixel's footprint (WEAR_TAPS)
    vec2 uv = (xy - wear_xform.xy) * wear_xform.zw;
    vec2 size = vec2(textureSize(wear_map, 0));
    vec2 dx = dFdx(uv), dy = dFdy(uv);
    float lx = length(dx * size), ly = length(dy * size);  // the footprint's axes in texels
    vec2 major = lx >= ly ? dx : dy;
    // as many lookups as the footprint is longer than wide (a road seen from above: one)
    float n = min(ceil(max(lx, ly) / max(min(lx, ly), 1e-6)), %WEAR_TAPS%.0);
    float lod = log2(max(max(lx, ly) / n, min(lx, ly)));
    vec2 w = vec2(0.0);
    for (float k = 0.5; k < n; k += 1.0)
        w += textureLod(wear_map, uv + major * (k / n - 0.5), lod).rg;
    return w / n;
}
const vec3 SNOW_ALBEDO = vec3(%SNOW%);
const float SNOW_BLEND = %SNOW_MIX%;
vec2 N(vec2 p) { return texture(noise, p * (1.0 / %NOISE%.0)).rg; }
float H(vec2 cell) { return texelFetch(noise, ivec2(mod(cell, %NOISE%.0)), 0).r; }  // one value a cell
float roofline(float z) {  // sine of the elevation of the opposite roofline seen from height z
    float h = max(canyon.x - z, 0.0);
    return h * inversesqrt(h * h + canyon.z * canyon.z + 1e-4);
}
vec3 sky_along(vec3 r, float z) {  // what a mirror at height z shows in direction r
    // the sky above the street canyon's opposite roofline; below it facades and street, lit
    // mostly by the sky (about a fifth of the horizon's radiance), as below the horizon
    vec3 sky = mix(horizon, zenith, sqrt(clamp(r.z, 0.0, 1.0)));
    float e = roofline(z);
    return mix(horizon * 0.18, sky, smoothstep(e - 0.08, e + 0.08, r.z) * step(0.0, r.z));
}
float sky_view(vec3 P, vec3 n) {  // the share of the open sky's light reaching P (face normal n)
    // the city's sky-view map (raster_backend.sky_view_map): at the ground or roof under P for
    // faces looking up, in front of the face for walls, rising to the whole sky at roof height
    vec2 q = (P.xy + (n.z > 0.5 ? vec2(0.0) : n.xy * svf_xform.w) - svf_xform.xy) * svf_xform.z;
    float g = texture(svf_map, q).r;
    float across = mix(1.0 - roofline(P.z), 1.0, smoothstep(canyon.y, 1.0, g));
    return n.z > 0.5 ? g : min(mix(g, 1.0, smoothstep(0.0, max(canyon.x, 1e-3), P.z)), across);
}
vec3 surface(int kind, vec4 prm, vec4 a, vec3 c, vec3 base, vec3 P, vec3 n, vec3 v, float fp, out vec3 reflected) {
    bool up = n.z > 0.5;
    float s = dot(P.xy, vec2(-n.y, n.x));  // along a vertical face
    vec2 uv = up ? P.xy : vec2(s, P.z);
    vec2 n1 = N(uv * (up ? vec2(0.6) : vec2(0.8, 0.06)));  // facades: vertical rain streaks
    vec2 n2 = N(uv * 9.0 + 31.7);
    float lo = n1.x - 0.5;
    float big = n1.y;  // features 12 cells wide: 20 m on the ground
    float hi = n2.x - 0.5;
    float fine = n2.y - 0.5;  // 0.75 cells a metre, a second mid octave
    float m = (1.0 + 2.0 * a.x * lo) * (1.0 + 2.0 * a.y * hi) * (1.0 + 2.0 * a.z * fine);
    // asphalt and roofs: darker resurfaced or repaired stretches and lighter worn ones (tens of
    // metres: a city's roads and roofs are a patchwork of ages); grass: dry patches (below)
    m *= mix(1.0, mix(1.0, 0.55, smoothstep(0.56, 0.6, big)) * mix(1.0, 1.3, smoothstep(0.42, 0.22, big)), a.w * float(kind == 1 || kind == 7));
    // roofs by building: a dark bitumen or rubber membrane (3 in 10); flat roofs also light gravel
    // ballast (1 in 10) or a white reflective membrane (2 in 10: cool roofs), set below
    float rv = fract(prm.z * 7.31);
    float flat_roof = float(kind == 7 && n.z > 0.98) * (1.0 - snow_cover);
    m *= mix(1.0, rv < 0.3 ? 0.45 : 1.0, float(kind == 7 && up));
    // tiles (paving, slabs: prm.y square), kerb stones (1 m), windows (prm.w wide, a storey high)
    vec2 tile = up ? prm.yy : vec2(kind == 3 ? 1.0 : prm.w, prm.y);
    vec2 t = uv / tile;
    vec2 e2 = min(fract(t), 1.0 - fract(t)) * tile;
    float cell = H(floor(t) + vec2(97.0 * prm.z + 11.0, 0.0));  // one value a tile, pane or stone
    float e = up ? min(e2.x, e2.y) : e2.x;
    float joint = (1.0 - smoothstep(c.z, c.z + fp, e)) * (1.0 - smoothstep(2.0 * c.z, 12.0 * c.z, fp));
    m *= (1.0 + 2.0 * c.x * (cell - 0.5)) * (1.0 - c.y * joint);
    // facades: a band at each floor slab (lighter or darker by variant), a darker plinth, grime
    float facade = float(kind == 5 && !up && n.z > -0.5);
    float fz = fract(P.z / prm.y) * prm.y;
    float band = smoothstep(0.32 + 0.5 * fp, 0.32 - 0.5 * fp, fz) * (1.0 - smoothstep(0.3, 0.8, fp));
    m *= mix(1.0, mix(1.0, prm.z < 0.5 ? 0.72 : 1.22, band) * mix(0.68, 1.0, smoothstep(0.7, 0.9, P.z))
                  * (0.8 + 0.2 * smoothstep(0.0, 2.5, P.z)), facade);
    // Snow on the ground (roads, markings, paving, grass, plazas: their materials come blended
    // SNOW_BLEND * snow_cover towards SNOW_ALBEDO by materials.weathered, undone here to the bare,
    // wet ground): a partial cover lies in patches, snow_cover of the area (where the 20 m noise,
    // ragged by the fine one, is under it), not as a grey wash; it goes on white over the ground's
    // own pattern below. Other faces looking up (roofs) keep the blend, their texture hidden.
    // (SNOW: the build for frames with snow; without, all of it is the identity and left out)
#ifdef SNOW
    bool ground = up && (kind == 1 || kind == 2 || kind == 3 || kind == 4 || kind == 10);
    float k_snow = SNOW_BLEND * snow_cover;
    float field = clamp(big + 0.12 * hi, 0.04, 0.96);  // no snow at all without cover, everywhere at full cover
    float lying = smoothstep(field - 0.03, field + 0.03, snow_cover);
    m = mix(m, 1.0, snow_cover * float(up && !ground));
    vec3 albedo = (ground ? (base - SNOW_ALBEDO * k_snow) / (1.0 - k_snow) : base) * m;
    if (kind == 1 || kind == 2) {  // tyres clear the snow off their tracks, markings included
        vec2 w = wear(P.xy);
        lying *= 1.0 - WEAR_CLEARED * w.y;
#else
    vec3 albedo = base * m;
    if (kind == 1) {
        vec2 w = wear(P.xy);
#endif
        // asphalt: traffic's oil, rubber and gutter grime (paint's own wear is its pattern's, below)
        albedo *= 1.0 - float(kind == 1) * (WEAR_STAIN * w.x + WEAR_RUBBER * w.y - WEAR_STAIN * WEAR_RUBBER * w.x * w.y);
    }
    albedo = mix(albedo, (rv > 0.8 ? vec3(0.62, 0.62, 0.6) : vec3(0.34, 0.33, 0.31)) * m, flat_roof * step(0.7, rv));
    // kerb stones are granite, lighter than the paving
    albedo = mix(albedo, vec3(0.36, 0.355, 0.34) * m, 0.7 * float(kind == 3 && !up));
    // road paint worn where wheels pass: asphalt shows through
    albedo = mix(albedo, vec3(0.09), 0.6 * float(kind == 2) * smoothstep(0.5, 0.9, 0.55 * (lo + 0.5) + 0.45 * (hi + 0.5)));
    // grass: dry patches; foliage: some clusters yellower
    albedo = mix(albedo, vec3(0.15, 0.13, 0.06) * m, 0.65 * float(kind == 4) * smoothstep(0.55, 0.8, big));
    albedo = mix(albedo, albedo * vec3(1.5, 1.25, 0.55), float(kind == 8) * smoothstep(0.1, 0.3, hi));
#ifdef SNOW
    albedo = mix(albedo, SNOW_ALBEDO, SNOW_BLEND * lying * float(ground));
#endif
    // windows: in daylight rooms behind glass are dark (most panes); a few show light blinds or
    // curtains (a value per pane); the sky and the facades opposite mirrored in front (glass's
    // Fresnel reflectance: 4% head-on, most of it at grazing angles); car paint: a clear coat
    float glass = float(kind == 6);
    float c2 = cell * cell;
    albedo *= mix(1.0, 0.15 + 4.0 * c2 * c2 * cell, glass);
    vec3 r = reflect(-v, n);
    float F = 0.04 + 0.96 * pow(1.0 - clamp(abs(dot(n, v)), 0.0, 1.0), 5.0);
    reflected = sky_along(r, P.z) * (glass * F * (0.3 + 0.7 * step(0.3, cell)) + float(kind == 9) * 0.8 * F);
    return albedo;
}
""".replace("%WEAR_STAIN%", f"{WEAR_STAIN:.6f}").replace("%WEAR_TAPS%", str(WEAR_TAPS)).replace("%WEAR_RUBBER%", f"{WEAR_RUBBER:.6f}").replace(
    "%WEAR_CLEARED%", f"{WEAR_CLEARED:.6f}").replace("%SNOW%", ", ".join(f"{c:.6f}" for c in SNOW)).replace(
    "%SNOW_MIX%", f"{SNOW_BLEND:.6f}")



# pyrender 0.1.45's metallic-roughness shading (one directional sun) with what the preview adds:
# procedural surfaces, the sun's shadow map (PCF), a sky/ground hemisphere ambient, street lamps
# at night and the camera's exposure; then fog over the ray length, in linear colour.
_COLOR_FS = """#version 330 core
const float PI = 3.141592653589793;
const float min_roughness = 0.04;
in vec3 shadow_coord;
in vec3 frag_position;
flat in vec4 base_metal;
flat in vec4 emis_rough;
flat in vec4 pattern;
flat in vec4 amp;
flat in vec3 cell_w;
uniform vec3 cam_pos;
uniform vec3 light_direction;
uniform vec3 light_radiance;
uniform vec3 sky_ambient;
uniform vec3 ground_ambient;
uniform vec3 zenith;
uniform vec3 horizon;
uniform vec3 canyon;
uniform float aureole;  // the share of the sky's light from round the sun, hidden with it (raster_backend.aureole_share)
uniform vec3 sky_wall;  // a wall's share of the sky's light: a + b cos(phi) + c cos^2(phi), phi its azimuth from the sun's
uniform sampler2D svf_map;
uniform vec4 svf_xform;  // map origin x, y (m), 1 / its side (m), the cell (m)
uniform sampler2D wear_map;  // what traffic leaves on the roads: r stain, g wheel tracks (road_wear.py)
uniform vec4 wear_xform;  // map origin x, y (m), 1 / its width, 1 / its height (m)
uniform float exposure;
uniform float snow_cover;
uniform int effects;
uniform float fog_density;
uniform vec3 fog_color;
uniform mat4 shadow_matrix;
uniform float normal_bias;
uniform sampler2DShadow shadow_map;
uniform sampler2D noise;
uniform float shadow_radius;
uniform int n_lamps;
uniform vec4 lamps[%LAMPS%];
uniform vec3 lamp_color;
out vec4 frag_color;
// A build per surface pattern (KIND defined) draws the static parts of that pattern: the compiler
// drops every other pattern's terms (llvmpipe would run them all, masked). The agents' build
// (AGENTS) reads the pattern per vertex and knows only theirs: plain and car paint.
#ifdef KIND
#define SURFACE_KIND KIND
#else
#define SURFACE_KIND int(pattern.x + 0.5)
#define SURFACE_AMP amp
#define SURFACE_CELL cell_w
#endif
%SURFACES%
%SRGB%
float sun_visibility(vec3 q) {
    if (q.x <= 0.0 || q.y <= 0.0 || q.x >= 1.0 || q.y >= 1.0 || q.z >= 1.0) return 1.0;
    vec2 r = vec2(0.7, 0.35) * shadow_radius;  // two bilinear (2x2) PCF taps: an 8-texel penumbra
    return 0.5 * (texture(shadow_map, vec3(q.xy + r, q.z)) + texture(shadow_map, vec3(q.xy - r, q.z)));
}
void main() {
    vec3 P = frag_position;
    float roughness = clamp(emis_rough.a, min_roughness, 1.0);
    float metallic = clamp(base_metal.a, 0.0, 1.0);
    // The face's normal from the position's screen derivatives (flat shading without per-face
    // vertex copies); it faces the camera, as every drawn face does (back faces are culled).
    vec3 n = normalize(cross(dFdx(P), dFdy(P)));
    vec3 v = normalize(cam_pos - P);
    float fp = max(length(fwidth(P)), 1e-4);
    vec3 reflected;
#ifdef AGENTS
    // agents' parts are plain or car paint (materials.agent_surface): surface() reduced to those two
    vec3 base = base_metal.rgb;
    float F_coat = 0.04 + 0.96 * pow(1.0 - clamp(abs(dot(n, v)), 0.0, 1.0), 5.0);
    reflected = sky_along(reflect(-v, n), P.z) * (0.0 + float(int(pattern.x + 0.5) == 9) * 0.8 * F_coat);
#else
    vec3 base = surface(SURFACE_KIND, pattern, SURFACE_AMP, SURFACE_CELL, base_metal.rgb, P, n, v, fp, reflected);
#endif
    vec3 c_diff = mix(vec3(0.0), base * (1 - min_roughness), 1.0 - metallic);
    vec3 f0 = mix(vec3(min_roughness), base, metallic);
    vec3 l = normalize(-1.0 * light_direction);
    vec3 h = normalize(l + v);
    float nl = clamp(dot(n, l), 0.001, 1.0);
    float nv = clamp(abs(dot(n, v)), 0.001, 1.0);
    float nh = clamp(dot(n, h), 0.0, 1.0);
    float vh = clamp(dot(v, h), 0.0, 1.0);
    vec3 F = f0 + (1.0 - f0) * pow(clamp(1.0 - vh, 0.0, 1.0), 5.0);
    float r = roughness + 1.0;
    float k = r * r / 8.0;
    float G = (nv / (nv * (1.0 - k) + k)) * (nl / (nl * (1.0 - k) + k));
    float a = roughness * roughness;
    float a2 = a * a;
    float denom = (nh * nh * (a2 - 1.0) + 1.0);
    float D = a2 / (PI * denom * denom);
    vec3 diffuse_contrib = (1.0 - F) * c_diff / PI;
    vec3 spec_contrib = F * G * D / (4.0 * nl * nv + 0.001);
#ifdef SHADOWS
    float sun = dot(n, l) > 0.0 ? sun_visibility(shadow_coord + mat3(shadow_matrix) * n * normal_bias) : 1.0;
#else
    float sun = 1.0;  // no shadow pass this frame (a uniform test would still pay for the lookup)
#endif
    vec3 color = sun * nl * light_radiance * (diffuse_contrib + spec_contrib);
    float sv = sky_view(P, n);
    // the sky's light on a face, as a share of a roof's: w_wall (1 - n_z^2) + n_z (1 + n_z) / 2,
    // exact for an evenly bright sky (w_wall 0.5) and for the CIE overcast sky (0.397); a clear
    // sky's wall share follows the CIE clear sky by the wall's azimuth from the sun (sky_wall)
    vec2 sun_h = -light_direction.xy;
    float cphi = dot(normalize(n.xy + vec2(1e-6, 0.0)), sun_h * inversesqrt(max(dot(sun_h, sun_h), 1e-12)));
    float w_wall = sky_wall.x + (sky_wall.y + sky_wall.z * cphi) * cphi;
    float w_sky = w_wall * (1.0 - n.z * n.z) + 0.5 * n.z * (1.0 + n.z);
    color += base * (ground_ambient * (0.5 - 0.5 * n.z)
                     + w_sky * (sky_ambient * mix(sv, dot(n, l) > 0.0 ? sun : sv, aureole) + ground_ambient * ((1.0 - sv) * float(n.z <= 0.5))));
    color += reflected * (sky_ambient.g > 0.0 ? 1.0 : 0.0);
#ifdef LAMPS
    for (int i = 0; i < %LAMPS%; ++i) {  // street lamps: downward lights, inverse-square falloff
        if (i >= n_lamps) break;
        vec3 d = lamps[i].xyz - P;
        float d2 = dot(d, d);
        vec3 ld = d * inversesqrt(d2);
        color += base * lamp_color * (lamps[i].w * max(dot(n, ld), 0.0) * smoothstep(0.15, 0.6, ld.z) / (d2 + 1.0));
    }
#endif
    color = color * exposure + emis_rough.rgb;
    if (effects != 0) {  // fog and haze over the ray length, in linear colour
        float T = exp(-fog_density * length(P - cam_pos));
        color = color * T + fog_color * exposure * (1.0 - T);
    }
    frag_color = vec4(encode(color), 1.0);
}
""".replace("%SURFACES%", _SURFACES_GLSL).replace("%LAMPS%", str(MAX_LAMPS)).replace("%NOISE%", str(NOISE_SIZE)).replace(
    "%SRGB%", _SRGB_GLSL)

# Contact shadows: a soft dark quad on the ground under each agent, drawn over the finished
# surfaces (no depth write; multiplies what is there). Under a car hardly any sky reaches the road:
# the dark band that makes a car sit on it in every light, overcast and night included.
_DECAL_VS = """#version 330 core
layout(location = 0) in vec3 position;
layout(location = 1) in vec2 uv;
uniform mat4 VP;
out vec2 f_uv;
void main() {
    gl_Position = VP * vec4(position, 1.0);
    f_uv = uv;
}
"""

_DECAL_FS = """#version 330 core
in vec2 f_uv;
uniform float strength;
out vec4 frag_color;
void main() {
    vec2 a = abs(f_uv);
    float e = length(max(a - 0.7, 0.0)) / 0.3;  // 0 over the core (the footprint), 1 at the edge
    frag_color = vec4(0.0, 0.0, 0.0, strength * (1.0 - smoothstep(0.0, 1.0, e)));
}
"""

_SHADOW_VS = """#version 330 core
layout(location = 0) in vec3 position;
uniform mat4 LVP;
void main() { gl_Position = LVP * vec4(position, 1.0); }
"""

_SHADOW_FS = """#version 330 core
void main() {}
"""

# The sky: one screen-covering triangle at the far plane, drawn last where nothing else was.
_SKY_VS = """#version 330 core
void main() {
    vec2 p = vec2(gl_VertexID == 1 ? 3.0 : -1.0, gl_VertexID == 2 ? 3.0 : -1.0);
    gl_Position = vec4(p, 1.0, 1.0);
}
"""

_SKY_FS = """#version 330 core
uniform mat3 ndc_to_world;  // (x_ndc, y_ndc, 1) -> a world ray through that point
uniform vec2 viewport;
uniform vec3 zenith;
uniform vec3 horizon;
uniform vec3 fog_color;
uniform float sky_transmittance;
uniform float exposure;
out vec4 frag_color;
%SRGB%
void main() {
    vec2 ndc = 2.0 * gl_FragCoord.xy / viewport - 1.0;
    vec3 d = normalize(ndc_to_world * vec3(ndc, 1.0));
    float e = clamp(d.z, 0.0, 1.0);
    vec3 sky = horizon * (1.0 - e) * (1.0 - e) + zenith * (1.0 - (1.0 - e) * (1.0 - e));
    vec3 c = (sky * sky_transmittance + fog_color * (1.0 - sky_transmittance)) * exposure;
    frag_color = vec4(encode(c), 1.0);
}
""".replace("%SRGB%", _SRGB_GLSL)

_ID_VS = """#version 330 core
layout(location = 0) in vec3 position;
layout(location = 3) in float instance;
uniform mat4 VP;
uniform int has_ids;
flat out uint frag_id;
void main() {
    gl_Position = VP * vec4(position, 1.0);
    frag_id = has_ids != 0 ? uint(instance + 0.5) : 0u;
}
"""

_ID_FS = """#version 330 core
flat in uint frag_id;
out uint out_id;
void main() { out_id = frag_id; }
"""


def _read_pixels(width: int, height: int, fmt: int, gl_type: int, dtype, channels: int) -> np.ndarray:
    """The bound read framebuffer into a new (H, W, channels) array, bottom row first."""
    out = np.empty((height, width, channels), dtype=dtype)
    gl.glPixelStorei(gl.GL_PACK_ALIGNMENT, 1)
    gl.glReadPixels(0, 0, width, height, fmt, gl_type, out)
    return out


def _program(vs: str, fs: str) -> int:
    from OpenGL.GL import shaders

    return shaders.compileProgram(shaders.compileShader(vs, gl.GL_VERTEX_SHADER), shaders.compileShader(fs, gl.GL_FRAGMENT_SHADER),
                                  validate=False)


class _Mesh:
    """One indexed vertex array: positions, material slots, (optionally) instance ids and the surface
    pattern rows (materials.Surface.row: fixed per part, so not in the per-frame table), and the
    triangles as indices into them.

    Vertices are shared between a part's faces (no per-face copies for flat shading): the colour
    shader takes each face's normal from the screen-space derivatives of its position, so a city
    is about a third of the vertices a triangle soup needs. Ranges are index ranges (first index,
    index count); each part's and each agent's triangles are contiguous.
    """

    def __init__(self) -> None:
        self.vao = gl.glGenVertexArrays(1)
        self.buffers = list(gl.glGenBuffers(5))
        self.count = 0  # indices
        self._offset_buffer = (ctypes.c_void_p * 64)()  # draw_ranges' offsets (_offsets)

    def upload(self, positions: np.ndarray, triangles: np.ndarray, slots: np.ndarray, ids: np.ndarray | None,
               surfaces: np.ndarray | None = None) -> None:
        gl.glBindVertexArray(self.vao)
        surf = None if surfaces is None else surface_attributes(surfaces)
        arrays = [(0, positions, 3), (2, slots, 1), (3, ids, 1), (4, surf, 12)]
        for (loc, data, size), buf in zip(arrays, self.buffers[:4]):
            if data is None:
                gl.glDisableVertexAttribArray(loc)
                continue
            data = np.ascontiguousarray(data, dtype=np.float32)
            gl.glBindBuffer(gl.GL_ARRAY_BUFFER, buf)
            gl.glBufferData(gl.GL_ARRAY_BUFFER, data.nbytes, data if data.size else None, gl.GL_STATIC_DRAW)
            for k in range(0, size, 4):  # 12 floats a vertex: three vec4 attributes (locations 4, 5, 6)
                gl.glEnableVertexAttribArray(loc + k // 4)
                gl.glVertexAttribPointer(loc + k // 4, min(size - k, 4), gl.GL_FLOAT, gl.GL_FALSE, 4 * size if size > 4 else 0,
                                         ctypes.c_void_p(4 * k))
        index = np.ascontiguousarray(triangles, dtype=np.uint32).reshape(-1)
        gl.glBindBuffer(gl.GL_ELEMENT_ARRAY_BUFFER, self.buffers[4])
        gl.glBufferData(gl.GL_ELEMENT_ARRAY_BUFFER, index.nbytes, index if index.size else None, gl.GL_STATIC_DRAW)
        gl.glBindVertexArray(0)
        self.count = len(index)

    def draw(self, ranges: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """All triangles, or only the index ranges (first, count) given."""
        if ranges is not None:
            self.draw_ranges(*ranges)
        elif self.count:
            gl.glBindVertexArray(self.vao)
            gl.glDrawElements(gl.GL_TRIANGLES, self.count, gl.GL_UNSIGNED_INT, ctypes.c_void_p(0))

    def draw_ranges(self, first: np.ndarray, count: np.ndarray) -> None:
        if len(first):
            gl.glBindVertexArray(self.vao)
            gl.glMultiDrawElements(gl.GL_TRIANGLES, np.ascontiguousarray(count, dtype=np.int32), gl.GL_UNSIGNED_INT,
                                   self._offsets(first), len(first))

    def _offsets(self, first: np.ndarray) -> ctypes.Array:
        """The ranges' byte offsets (4 a uint32 index) in the mesh's one ctypes array, grown by
        doubling. Why one: PyOpenGL keeps a handler for every ctypes array type it is given, and
        (c_void_p * n) is a type of its own for each n, so an array made per draw kept ~3 KB for
        every range count a run met (tests/scenes/test_raster_speed.py)."""
        n = len(first)
        if len(self._offset_buffer) < n:
            self._offset_buffer = (ctypes.c_void_p * (1 << (n - 1).bit_length()))()
        np.frombuffer(self._offset_buffer, dtype=np.uintp)[:n] = 4 * np.asarray(first, dtype=np.uintp)
        return self._offset_buffer

    def delete(self) -> None:
        gl.glDeleteBuffers(len(self.buffers), self.buffers)
        gl.glDeleteVertexArrays(1, [self.vao])


@dataclass
class Light:
    """What lights a colour pass (linear rgb; radiance as pyrender's: diffuse = albedo / pi * nl * it).

    sky_ambient and ground_ambient light a face pointing up and down (mixed by its normal's z);
    zenith and horizon are the sky mirrored by glass and car paint; exposure scales all scene light
    (the camera's, not the surfaces'); emission is added after it, as drawn. shadow_lvp is the sun's
    light view-projection (None: no shadow pass); shadow_radius the PCF radius in shadow-map texels;
    normal_bias (m) moves the looked-up point off its face (no self-shadowing acne). lamps: (N, 4)
    xyz and intensity, point lights shining downwards.
    """

    direction: tuple = (0.0, 0.0, -1.0)
    radiance: tuple = (0.0, 0.0, 0.0)
    sky_ambient: tuple = (0.0, 0.0, 0.0)
    ground_ambient: tuple = (0.0, 0.0, 0.0)
    zenith: tuple = (0.0, 0.0, 0.0)
    horizon: tuple = (0.0, 0.0, 0.0)
    exposure: float = 1.0
    shadow_lvp: np.ndarray | None = None
    shadow_radius: float = 1.5
    normal_bias: float = 0.05
    lamps: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    lamp_color: tuple = (1.0, 0.82, 0.55)
    contact_shadow: float = 0.0  # darkening at the centre of the quads under agents (set_decals)
    snow_cover: float = 0.0  # of the ground (Weather.snow_cover): fades the ground's patterns
    sun_share: float = 0.0  # the sun's share of the daylight on a horizontal face (the backend's cue for shadows)
    # the city's street canyon: building height (m), the sky's share at street level, street width (m)
    # between facades; (0, 1, 1): open ground, the sky everywhere (sky_view, sky_along in the shader)
    canyon: tuple = (0.0, 1.0, 1.0)
    # where the sky-view map (GLRaster.set_sky_view) lies: origin x, y (m), 1 / side (m), cell (m)
    svf_xform: tuple = (0.0, 0.0, 1.0, 1.0)
    # a wall's share of the sky's light on a roof, a + b cos(phi) + c cos^2(phi) with phi the wall's
    # azimuth from the sun's (raster_backend.sky_on_walls); (0.5, 0, 0): an evenly bright sky
    sky_wall: tuple = (0.5, 0.0, 0.0)
    # where the road-wear map (GLRaster.set_road_wear) lies: origin x, y (m), 1 / width, 1 / height (m)
    wear_xform: tuple = (0.0, 0.0, 1.0, 1.0)
    aureole: float = 0.0  # the share of the sky's light from round the sun: a face sees it where it sees the sun
    max_gain: float = 1.0  # how far the camera's automatic exposure may open up (auto_exposure; 1: not at all)


_COLOR_UNIFORMS = ("VP", "materials", "wear_map", "wear_xform", "cam_pos", "light_direction", "light_radiance", "sky_ambient", "ground_ambient",
                   "zenith", "horizon", "canyon", "sky_wall", "aureole", "svf_map", "svf_xform", "exposure", "snow_cover", "effects", "fog_density", "fog_color",
                   "shadow_matrix", "shadow_map", "noise", "shadow_radius", "normal_bias", "n_lamps", "lamps", "lamp_color")


class GLRaster:
    """The GL context, programs, framebuffers and the two meshes; see the module doc."""

    def __init__(self) -> None:
        from pyrender.platforms.egl import EGLPlatform

        self._platform = EGLPlatform(1, 1)
        self._platform.init_context()
        self._platform.make_current()
        # Builds of the colour shader, made when first needed, per (surface pattern or None, lamps, snow,
        # shadows): llvmpipe pays for the lamp loop even when it runs no iteration (~100 ms of CPU
        # a 640x640 frame), for the shadow lookup behind a uniform test and for every pattern's
        # terms at every pixel, so each draw gets only what it needs.
        self._color_progs: dict[tuple[int | None, bool, bool, bool], tuple[int, dict]] = {}
        self._id_prog = _program(_ID_VS, _ID_FS)
        self._shadow_prog = _program(_SHADOW_VS, _SHADOW_FS)
        self._sky_prog = _program(_SKY_VS, _SKY_FS)
        self._decal_prog = _program(_DECAL_VS, _DECAL_FS)
        self._decal_loc = {name: gl.glGetUniformLocation(self._decal_prog, name) for name in ("VP", "strength")}
        self._decal_vao = gl.glGenVertexArrays(1)
        self._decal_bufs = list(gl.glGenBuffers(2))
        self._decal_count = 0
        self._sky_vao = gl.glGenVertexArrays(1)
        self.static = _Mesh()
        self.agents = _Mesh()
        # What of the static city to draw (vertex ranges; None: all), set per camera by the backend:
        # the parts whose bounds reach the view, and the shadow casters reaching the sun's map.
        self.static_view: tuple[np.ndarray, np.ndarray] | None = None
        self.static_shadow: tuple[np.ndarray, np.ndarray] | None = None
        self.static_view_kinds: np.ndarray | None = None  # the surface pattern of each static_view range
        self._materials = gl.glGenTextures(1)
        self._size: tuple[int, int] | None = None
        self._fbos: list[int] = []
        self._rbos: list[int] = []
        self._sky_loc = {name: gl.glGetUniformLocation(self._sky_prog, name)
                         for name in ("ndc_to_world", "viewport", "zenith", "horizon", "fog_color", "sky_transmittance",
                                      "exposure")}
        self._shadow_lvp_loc = gl.glGetUniformLocation(self._shadow_prog, "LVP")
        self._shadow_fbo, self._shadow_tex = self._shadow_target(SHADOW_SIZE)
        self._noise_tex = self._noise_texture()
        self._svf_tex = gl.glGenTextures(1)
        self.set_sky_view(np.ones((1, 1), dtype=np.float32))
        self._wear_tex = gl.glGenTextures(1)
        self.set_road_wear(np.zeros((1, 1, 2), dtype=np.uint8))
        self._id_loc = {name: gl.glGetUniformLocation(self._id_prog, name) for name in ("VP", "has_ids")}

    def make_current(self) -> None:
        self._platform.make_current()

    def _color_program(self, kind: int | None, lamps: bool, shadows: bool, snow: bool = False) -> tuple[int, dict]:
        """The colour shader built for one surface pattern (AGENT_KINDS: the agents', plain or car
        paint, read per vertex; None: any, read per vertex), with or without the lamp loop, the
        shadow lookup and the snow on the ground, and its uniform locations."""
        key = (kind, lamps, shadows, snow)
        if key not in self._color_progs:
            defines = (("#define LAMPS\n" if lamps else "") + ("#define SHADOWS\n" if shadows else "")
                       + ("#define SNOW\n" if snow else "")
                       + {None: "", AGENT_KINDS: "#define AGENTS\n"}.get(kind, _kind_defines(kind)))
            prog = _program(_COLOR_VS, _COLOR_FS.replace("#version 330 core\n", "#version 330 core\n" + defines, 1))
            loc = {name: gl.glGetUniformLocation(prog, name) for name in _COLOR_UNIFORMS}
            self._color_progs[key] = (prog, loc)
        return self._color_progs[key]

    @property
    def color_builds(self) -> int:
        """How many builds of the colour shader exist: each costs resident memory (llvmpipe keeps
        its compiled code) from the first frame that needs it on (bench_render.py --memory-frames)."""
        return len(self._color_progs)

    # -- data ---------------------------------------------------------------------------------

    def set_materials(self, table: np.ndarray) -> None:
        """(S, 8) float: base rgb, metallic, emission rgb (linear, as drawn), roughness per slot."""
        s = len(table)
        rows = max(1, -(-s // SLOTS_PER_ROW))
        tex = np.zeros((2 * rows, SLOTS_PER_ROW, 4), dtype=np.float32)
        idx = np.arange(s)
        y, x = 2 * (idx // SLOTS_PER_ROW), idx % SLOTS_PER_ROW
        tex[y, x] = table[:, :4]
        tex[y + 1, x] = table[:, 4:8]
        gl.glBindTexture(gl.GL_TEXTURE_2D, self._materials)
        gl.glTexParameteri(gl.GL_TEXTURE_2D, gl.GL_TEXTURE_MIN_FILTER, gl.GL_NEAREST)
        gl.glTexParameteri(gl.GL_TEXTURE_2D, gl.GL_TEXTURE_MAG_FILTER, gl.GL_NEAREST)
        gl.glTexImage2D(gl.GL_TEXTURE_2D, 0, gl.GL_RGBA32F, SLOTS_PER_ROW, 2 * rows, 0, gl.GL_RGBA, gl.GL_FLOAT, tex.tobytes())
        gl.glBindTexture(gl.GL_TEXTURE_2D, 0)

    def set_sky_view(self, svf: np.ndarray) -> None:
        """The city's sky-view map, (ny, nx) float in [0, 1], row j at y = y0 + (j + 0.5) cell
        (Light.svf_xform places it); outside it, its edge (the map has an open margin)."""
        a = np.ascontiguousarray(svf, dtype=np.float32)
        gl.glBindTexture(gl.GL_TEXTURE_2D, self._svf_tex)
        for name, value in ((gl.GL_TEXTURE_MIN_FILTER, gl.GL_LINEAR), (gl.GL_TEXTURE_MAG_FILTER, gl.GL_LINEAR),
                            (gl.GL_TEXTURE_WRAP_S, gl.GL_CLAMP_TO_EDGE), (gl.GL_TEXTURE_WRAP_T, gl.GL_CLAMP_TO_EDGE)):
            gl.glTexParameteri(gl.GL_TEXTURE_2D, name, value)
        gl.glTexImage2D(gl.GL_TEXTURE_2D, 0, gl.GL_R32F, a.shape[1], a.shape[0], 0, gl.GL_RED, gl.GL_FLOAT, a.tobytes())
        gl.glBindTexture(gl.GL_TEXTURE_2D, 0)

    def set_road_wear(self, wear: np.ndarray) -> None:
        """The city's road-wear map (road_wear.road_wear_map), (ny, nx, 2) uint8: stain and wheel
        tracks, row j at y = y0 + (j + 0.5) cell (Light.wear_xform places it); mipmapped, so a
        distant road averages its tracks instead of shimmering; outside it, its edge (zero)."""
        a = np.ascontiguousarray(wear, dtype=np.uint8)
        gl.glBindTexture(gl.GL_TEXTURE_2D, self._wear_tex)
        gl.glPixelStorei(gl.GL_UNPACK_ALIGNMENT, 1)
        gl.glTexImage2D(gl.GL_TEXTURE_2D, 0, gl.GL_RG8, a.shape[1], a.shape[0], 0, gl.GL_RG, gl.GL_UNSIGNED_BYTE, a.tobytes())
        gl.glGenerateMipmap(gl.GL_TEXTURE_2D)
        for name, value in ((gl.GL_TEXTURE_MIN_FILTER, gl.GL_LINEAR_MIPMAP_NEAREST), (gl.GL_TEXTURE_MAG_FILTER, gl.GL_LINEAR),
                            (gl.GL_TEXTURE_WRAP_S, gl.GL_CLAMP_TO_EDGE), (gl.GL_TEXTURE_WRAP_T, gl.GL_CLAMP_TO_EDGE)):
            gl.glTexParameteri(gl.GL_TEXTURE_2D, name, value)
        gl.glBindTexture(gl.GL_TEXTURE_2D, 0)

    def set_decals(self, positions: np.ndarray, uv: np.ndarray) -> None:
        """The contact-shadow quads as triangles: (N, 3) world positions and (N, 2) quad coordinates
        (-1..1 across the quad; the agent's footprint ends at about 0.6)."""
        gl.glBindVertexArray(self._decal_vao)
        for loc, data, size, buf in ((0, positions, 3, self._decal_bufs[0]), (1, uv, 2, self._decal_bufs[1])):
            data = np.ascontiguousarray(data, dtype=np.float32)
            gl.glBindBuffer(gl.GL_ARRAY_BUFFER, buf)
            gl.glBufferData(gl.GL_ARRAY_BUFFER, data.nbytes, data if data.size else None, gl.GL_DYNAMIC_DRAW)
            gl.glEnableVertexAttribArray(loc)
            gl.glVertexAttribPointer(loc, size, gl.GL_FLOAT, gl.GL_FALSE, 0, ctypes.c_void_p(0))
        gl.glBindVertexArray(0)
        self._decal_count = len(positions)

    def _decals(self, VP: np.ndarray, strength: float) -> None:
        if not self._decal_count or strength <= 0:
            return
        gl.glUseProgram(self._decal_prog)
        gl.glUniformMatrix4fv(self._decal_loc["VP"], 1, gl.GL_TRUE, np.asarray(VP, dtype=np.float32))
        gl.glUniform1f(self._decal_loc["strength"], float(strength))
        gl.glDepthFunc(gl.GL_LEQUAL)
        gl.glDepthMask(gl.GL_FALSE)
        gl.glDisable(gl.GL_CULL_FACE)
        gl.glEnable(gl.GL_POLYGON_OFFSET_FILL)
        gl.glPolygonOffset(-1.0, -4.0)
        gl.glEnable(gl.GL_BLEND)
        gl.glBlendFunc(gl.GL_ZERO, gl.GL_ONE_MINUS_SRC_ALPHA)  # what is there, darkened by alpha
        gl.glBindVertexArray(self._decal_vao)
        gl.glDrawArrays(gl.GL_TRIANGLES, 0, self._decal_count)
        gl.glDisable(gl.GL_BLEND)
        gl.glDisable(gl.GL_POLYGON_OFFSET_FILL)
        gl.glEnable(gl.GL_CULL_FACE)
        gl.glDepthMask(gl.GL_TRUE)
        gl.glDepthFunc(gl.GL_LESS)

    # -- framebuffers -------------------------------------------------------------------------

    @staticmethod
    def _noise_texture() -> int:
        """The value-noise table as a repeating, mipmapped single-channel float texture."""
        values = noise_table()
        tex = gl.glGenTextures(1)
        gl.glBindTexture(gl.GL_TEXTURE_2D, tex)
        gl.glTexImage2D(gl.GL_TEXTURE_2D, 0, gl.GL_RG32F, NOISE_SIZE, NOISE_SIZE, 0, gl.GL_RG, gl.GL_FLOAT, values.tobytes())
        gl.glGenerateMipmap(gl.GL_TEXTURE_2D)
        for name, value in ((gl.GL_TEXTURE_MIN_FILTER, gl.GL_LINEAR_MIPMAP_NEAREST), (gl.GL_TEXTURE_MAG_FILTER, gl.GL_LINEAR),
                            (gl.GL_TEXTURE_WRAP_S, gl.GL_REPEAT), (gl.GL_TEXTURE_WRAP_T, gl.GL_REPEAT)):
            gl.glTexParameteri(gl.GL_TEXTURE_2D, name, value)
        gl.glBindTexture(gl.GL_TEXTURE_2D, 0)
        return tex

    @staticmethod
    def _shadow_target(size: int) -> tuple[int, int]:
        """A depth texture (compared on lookup: hardware 2x2 PCF) and its framebuffer."""
        tex = gl.glGenTextures(1)
        gl.glBindTexture(gl.GL_TEXTURE_2D, tex)
        gl.glTexImage2D(gl.GL_TEXTURE_2D, 0, gl.GL_DEPTH_COMPONENT24, size, size, 0, gl.GL_DEPTH_COMPONENT, gl.GL_FLOAT, None)
        for name, value in ((gl.GL_TEXTURE_MIN_FILTER, gl.GL_LINEAR), (gl.GL_TEXTURE_MAG_FILTER, gl.GL_LINEAR),
                            (gl.GL_TEXTURE_WRAP_S, gl.GL_CLAMP_TO_EDGE), (gl.GL_TEXTURE_WRAP_T, gl.GL_CLAMP_TO_EDGE),
                            (gl.GL_TEXTURE_COMPARE_MODE, gl.GL_COMPARE_REF_TO_TEXTURE), (gl.GL_TEXTURE_COMPARE_FUNC, gl.GL_LEQUAL)):
            gl.glTexParameteri(gl.GL_TEXTURE_2D, name, value)
        gl.glBindTexture(gl.GL_TEXTURE_2D, 0)
        fbo = gl.glGenFramebuffers(1)
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, fbo)
        gl.glFramebufferTexture2D(gl.GL_FRAMEBUFFER, gl.GL_DEPTH_ATTACHMENT, gl.GL_TEXTURE_2D, tex, 0)
        gl.glDrawBuffer(gl.GL_NONE)
        gl.glReadBuffer(gl.GL_NONE)
        status = gl.glCheckFramebufferStatus(gl.GL_FRAMEBUFFER)
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, 0)
        if status != gl.GL_FRAMEBUFFER_COMPLETE:
            raise RuntimeError(f"shadow framebuffer incomplete: {status}")
        return fbo, tex

    def _framebuffers(self, width: int, height: int) -> None:
        if self._size == (width, height):
            return
        self._delete_framebuffers()
        self._rbos = list(gl.glGenRenderbuffers(5))
        self._fbos = list(gl.glGenFramebuffers(3))
        ms_color, ms_depth, color, ids, depth = self._rbos
        for rb, fmt, samples in ((ms_color, gl.GL_RGBA8, MSAA_SAMPLES), (ms_depth, gl.GL_DEPTH_COMPONENT24, MSAA_SAMPLES),
                                 (color, gl.GL_RGBA8, 0), (ids, gl.GL_R32UI, 0), (depth, gl.GL_DEPTH_COMPONENT24, 0)):
            gl.glBindRenderbuffer(gl.GL_RENDERBUFFER, rb)
            if samples:
                gl.glRenderbufferStorageMultisample(gl.GL_RENDERBUFFER, samples, fmt, width, height)
            else:
                gl.glRenderbufferStorage(gl.GL_RENDERBUFFER, fmt, width, height)
        for fb, c, d in zip(self._fbos, (ms_color, color, ids), (ms_depth, None, depth)):
            gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, fb)
            gl.glFramebufferRenderbuffer(gl.GL_FRAMEBUFFER, gl.GL_COLOR_ATTACHMENT0, gl.GL_RENDERBUFFER, c)
            if d is not None:
                gl.glFramebufferRenderbuffer(gl.GL_FRAMEBUFFER, gl.GL_DEPTH_ATTACHMENT, gl.GL_RENDERBUFFER, d)
            status = gl.glCheckFramebufferStatus(gl.GL_FRAMEBUFFER)
            if status != gl.GL_FRAMEBUFFER_COMPLETE:
                raise RuntimeError(f"framebuffer incomplete: {status}")
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, 0)
        self._size = (width, height)

    def _delete_framebuffers(self) -> None:
        if self._fbos:
            gl.glDeleteFramebuffers(len(self._fbos), self._fbos)
            gl.glDeleteRenderbuffers(len(self._rbos), self._rbos)
        self._fbos, self._rbos, self._size = [], [], None

    # -- passes -------------------------------------------------------------------------------

    @staticmethod
    def _state() -> None:
        gl.glEnable(gl.GL_DEPTH_TEST)
        gl.glDepthFunc(gl.GL_LESS)
        gl.glDepthMask(gl.GL_TRUE)
        gl.glEnable(gl.GL_CULL_FACE)
        gl.glCullFace(gl.GL_BACK)
        gl.glDisable(gl.GL_BLEND)

    def shadow_pass(self, lvp: np.ndarray) -> None:
        """The sun's depth map: the static city and this frame's agents seen along the sunlight.

        No face culling (the ground and markings are single faces) and a slope-scaled depth offset:
        with the lookup's normal offset, lit faces do not shadow themselves.
        """
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, self._shadow_fbo)
        gl.glViewport(0, 0, SHADOW_SIZE, SHADOW_SIZE)
        self._state()
        gl.glDisable(gl.GL_CULL_FACE)
        gl.glDisable(gl.GL_MULTISAMPLE)
        gl.glEnable(gl.GL_POLYGON_OFFSET_FILL)
        gl.glPolygonOffset(1.5, 4.0)
        gl.glClear(gl.GL_DEPTH_BUFFER_BIT)
        gl.glUseProgram(self._shadow_prog)
        gl.glUniformMatrix4fv(self._shadow_lvp_loc, 1, gl.GL_TRUE, np.asarray(lvp, dtype=np.float32))
        self.static.draw(self.static_shadow)
        self.agents.draw()
        gl.glDisable(gl.GL_POLYGON_OFFSET_FILL)
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, 0)

    def color_pass(self, VP: np.ndarray, cam_pos, light: Light, width: int, height: int,
                   atmosphere: dict | None = None) -> np.ndarray:
        """The shaded image, (H, W, 3) uint8 (top row first); the sun's shadow pass first when
        `light.shadow_lvp` is given.

        `atmosphere` (None: none; background black): fog_density (1/m), fog_color, zenith and
        horizon (linear rgb), sky_distance (m) and ndc_to_world (3x3, see _SKY_FS).
        """
        return self.color_draw(VP, cam_pos, light, width, height, atmosphere)()

    def color_draw(self, VP: np.ndarray, cam_pos, light: Light, width: int, height: int,
                   atmosphere: dict | None = None) -> Callable[[], np.ndarray]:
        """color_pass's draw calls, handed to the rasteriser without waiting for them; returns the
        read-back (the multisample resolve and the read) that gives color_pass's image. Why:
        llvmpipe rasterises on threads of its own, so Python work done between the two (the next
        frame's scene) runs while the frame is shaded. Call the read-back before the next colour
        pass (it resolves this pass's framebuffer)."""
        shadows = light.shadow_lvp is not None
        if shadows:
            self.shadow_pass(light.shadow_lvp)

        self._framebuffers(width, height)
        ms_fb, color_fb, _ = self._fbos
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, ms_fb)
        gl.glViewport(0, 0, width, height)
        self._state()
        gl.glEnable(gl.GL_MULTISAMPLE)
        gl.glClearColor(0.0, 0.0, 0.0, 0.0)
        gl.glClear(gl.GL_COLOR_BUFFER_BIT | gl.GL_DEPTH_BUFFER_BIT)
        lamps = np.asarray(light.lamps, dtype=np.float32).reshape(-1, 4)[:MAX_LAMPS]
        gl.glActiveTexture(gl.GL_TEXTURE1)
        gl.glBindTexture(gl.GL_TEXTURE_2D, self._shadow_tex)
        gl.glActiveTexture(gl.GL_TEXTURE2)
        gl.glBindTexture(gl.GL_TEXTURE_2D, self._noise_tex)
        gl.glActiveTexture(gl.GL_TEXTURE3)
        gl.glBindTexture(gl.GL_TEXTURE_2D, self._svf_tex)
        gl.glActiveTexture(gl.GL_TEXTURE4)
        gl.glBindTexture(gl.GL_TEXTURE_2D, self._wear_tex)
        gl.glActiveTexture(gl.GL_TEXTURE0)
        gl.glBindTexture(gl.GL_TEXTURE_2D, self._materials)
        groups: list[tuple[int | None, _Mesh, tuple | None]] = []
        if self.static_view is not None and self.static_view_kinds is not None:
            first, count = self.static_view
            kinds = np.asarray(self.static_view_kinds)
            for k in np.unique(kinds):
                sel = kinds == k
                groups.append((int(k), self.static, (first[sel], count[sel])))
        else:
            groups.append((None, self.static, self.static_view))  # every pattern, read per vertex
        groups.append((AGENT_KINDS, self.agents, None))
        for kind, mesh, ranges in groups:
            prog, loc = self._color_program(kind, len(lamps) > 0, shadows, light.snow_cover > 0)
            gl.glUseProgram(prog)
            self._color_uniforms(loc, VP, cam_pos, light, atmosphere, lamps, shadows)
            mesh.draw(ranges)
        self._decals(VP, light.contact_shadow)
        if atmosphere is not None:
            self._sky(atmosphere, width, height, light.exposure)
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, 0)
        gl.glFlush()  # hand the pass to the rasteriser's threads; the resolve below waits for it
        max_gain, effects = light.max_gain, atmosphere is not None

        def read() -> np.ndarray:
            self.make_current()
            gl.glBindFramebuffer(gl.GL_READ_FRAMEBUFFER, ms_fb)
            gl.glBindFramebuffer(gl.GL_DRAW_FRAMEBUFFER, color_fb)
            gl.glBlitFramebuffer(0, 0, width, height, 0, 0, width, height, gl.GL_COLOR_BUFFER_BIT, gl.GL_NEAREST)
            gl.glBindFramebuffer(gl.GL_READ_FRAMEBUFFER, color_fb)
            rgba = _read_pixels(width, height, gl.GL_RGBA, gl.GL_UNSIGNED_BYTE, np.uint8, 4)
            gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, 0)
            rgb = rgba[::-1, :, :3]
            return auto_exposure(rgb, max_gain) if effects else rgb

        return read

    @staticmethod
    def _color_uniforms(loc: dict, VP, cam_pos, light: Light, atmosphere: dict | None, lamps: np.ndarray, shadows: bool) -> None:
        vec3 = lambda name, x: gl.glUniform3f(loc[name], *(float(c) for c in x))  # noqa: E731
        gl.glUniformMatrix4fv(loc["VP"], 1, gl.GL_TRUE, np.asarray(VP, dtype=np.float32))
        vec3("cam_pos", cam_pos)
        vec3("light_direction", light.direction)
        vec3("light_radiance", light.radiance)
        vec3("sky_ambient", light.sky_ambient)
        vec3("ground_ambient", light.ground_ambient)
        vec3("zenith", light.zenith)
        vec3("horizon", light.horizon)
        vec3("canyon", light.canyon)
        vec3("lamp_color", light.lamp_color)
        gl.glUniform1f(loc["exposure"], float(light.exposure))
        gl.glUniform1f(loc["snow_cover"], float(light.snow_cover))
        vec3("sky_wall", light.sky_wall)
        gl.glUniform1f(loc["aureole"], float(light.aureole))
        gl.glUniform1i(loc["effects"], int(atmosphere is not None))
        if atmosphere is not None:
            gl.glUniform1f(loc["fog_density"], float(atmosphere["fog_density"]))
            vec3("fog_color", atmosphere["fog_color"])
        gl.glUniform1i(loc["n_lamps"], len(lamps))
        if len(lamps):
            gl.glUniform4fv(loc["lamps"], len(lamps), np.ascontiguousarray(lamps))
        gl.glUniform1i(loc["materials"], 0)
        gl.glUniform1i(loc["shadow_map"], 1)
        gl.glUniform1i(loc["noise"], 2)
        gl.glUniform1i(loc["svf_map"], 3)
        gl.glUniform4f(loc["svf_xform"], *(float(x) for x in light.svf_xform))
        gl.glUniform1i(loc["wear_map"], 4)
        gl.glUniform4f(loc["wear_xform"], *(float(x) for x in light.wear_xform))
        if shadows:
            bias = np.array([[0.5, 0, 0, 0.5], [0, 0.5, 0, 0.5], [0, 0, 0.5, 0.5], [0, 0, 0, 1.0]])
            gl.glUniformMatrix4fv(loc["shadow_matrix"], 1, gl.GL_TRUE, np.asarray(bias @ light.shadow_lvp, dtype=np.float32))
            gl.glUniform1f(loc["shadow_radius"], float(light.shadow_radius) / SHADOW_SIZE)
            gl.glUniform1f(loc["normal_bias"], float(light.normal_bias))

    def _sky(self, a: dict, width: int, height: int, exposure: float) -> None:
        gl.glUseProgram(self._sky_prog)
        loc = self._sky_loc
        gl.glUniformMatrix3fv(loc["ndc_to_world"], 1, gl.GL_TRUE, np.asarray(a["ndc_to_world"], dtype=np.float32))
        gl.glUniform2f(loc["viewport"], float(width), float(height))
        for name in ("zenith", "horizon", "fog_color"):
            gl.glUniform3f(loc[name], *(float(x) for x in a[name]))
        gl.glUniform1f(loc["sky_transmittance"], float(np.exp(-a["fog_density"] * a["sky_distance"])))
        gl.glUniform1f(loc["exposure"], float(exposure))
        gl.glDepthFunc(gl.GL_LEQUAL)
        gl.glDepthMask(gl.GL_FALSE)
        gl.glDisable(gl.GL_CULL_FACE)
        gl.glBindVertexArray(self._sky_vao)
        gl.glDrawArrays(gl.GL_TRIANGLES, 0, 3)
        gl.glDepthMask(gl.GL_TRUE)
        gl.glDepthFunc(gl.GL_LESS)

    def _id_setup(self, VP: np.ndarray, width: int, height: int) -> None:
        self._framebuffers(width, height)
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, self._fbos[2])
        gl.glViewport(0, 0, width, height)
        self._state()
        gl.glDisable(gl.GL_MULTISAMPLE)
        gl.glClearBufferuiv(gl.GL_COLOR, 0, np.zeros(4, dtype=np.uint32))
        gl.glClear(gl.GL_DEPTH_BUFFER_BIT)
        gl.glUseProgram(self._id_prog)
        gl.glUniformMatrix4fv(self._id_loc["VP"], 1, gl.GL_TRUE, np.asarray(VP, dtype=np.float32))

    def _read_ids(self, width: int, height: int) -> np.ndarray:
        ids = _read_pixels(width, height, gl.GL_RED_INTEGER, gl.GL_UNSIGNED_INT, np.uint32, 1)
        return ids[::-1, :, 0].astype(np.uint16)

    def id_static(self, VP: np.ndarray, width: int, height: int) -> np.ndarray:
        """First half of the id pass: clear, draw the static city; its camera z (what hides agents)."""
        self._id_setup(VP, width, height)
        gl.glUniform1i(self._id_loc["has_ids"], 0)
        self.static.draw(self.static_view)
        z = self._read_z(width, height)
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, 0)
        return z

    def id_agents(self, VP: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Second half of the id pass: the agents over the static city, then ids and camera z."""
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, self._fbos[2])
        gl.glViewport(0, 0, width, height)
        self._state()
        gl.glUseProgram(self._id_prog)
        gl.glUniformMatrix4fv(self._id_loc["VP"], 1, gl.GL_TRUE, np.asarray(VP, dtype=np.float32))
        gl.glUniform1i(self._id_loc["has_ids"], 1)
        self.agents.draw()
        ids = self._read_ids(width, height)
        z = self._read_z(width, height)
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, 0)
        return ids, z

    @staticmethod
    def _read_z(width: int, height: int) -> np.ndarray:
        d = _read_pixels(width, height, gl.GL_DEPTH_COMPONENT, gl.GL_FLOAT, np.float32, 1)[::-1, :, 0]
        ndc = 2.0 * d - 1.0
        with np.errstate(divide="ignore"):
            z = np.float32(2.0 * ZNEAR * ZFAR) / (np.float32(ZFAR + ZNEAR) - ndc * np.float32(ZFAR - ZNEAR))
        z[d >= 1.0] = np.inf
        return z.astype(np.float32, copy=False)

    def ids_of_ranges(self, VP: np.ndarray, width: int, height: int, first: np.ndarray, count: np.ndarray) -> np.ndarray:
        """Instance ids with only the given vertex ranges of the agent mesh drawn."""
        self._id_setup(VP, width, height)
        gl.glUniform1i(self._id_loc["has_ids"], 1)
        self.agents.draw_ranges(first, count)
        ids = self._read_ids(width, height)
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, 0)
        return ids

    def close(self) -> None:
        if self._platform is None:
            return
        self.make_current()
        self._delete_framebuffers()
        self.static.delete()
        self.agents.delete()
        gl.glDeleteTextures([self._materials, self._shadow_tex, self._noise_tex, self._svf_tex, self._wear_tex])
        gl.glDeleteFramebuffers(1, [self._shadow_fbo])
        for prog, _ in self._color_progs.values():
            gl.glDeleteProgram(prog)
        gl.glDeleteProgram(self._shadow_prog)
        gl.glDeleteProgram(self._id_prog)
        gl.glDeleteProgram(self._sky_prog)
        gl.glDeleteProgram(self._decal_prog)
        gl.glDeleteBuffers(2, self._decal_bufs)
        gl.glDeleteVertexArrays(1, [self._decal_vao])
        gl.glDeleteVertexArrays(1, [self._sky_vao])
        from OpenGL.EGL import eglDestroyContext

        # Only this context: terminating the display would invalidate other live contexts.
        eglDestroyContext(self._platform._egl_display, self._platform._egl_context)
        self._platform = None
