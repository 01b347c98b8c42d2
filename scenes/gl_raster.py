"""A minimal OpenGL 3.3 core rasteriser for the raster preview: a handful of draw calls a frame.

Why not pyrender's renderer: on software GL (Mesa llvmpipe) a frame's cost was Python work per
draw call (pyrender binds every uniform, light and material per primitive: ~0.35 ms a call,
~870 calls a colour pass) plus a multisampled segmentation pass and framebuffer reads nobody
used. Here the geometry is uploaded as two vertex buffers (the static city, once; this frame's
agents) whose vertices carry a material slot and an instance id; materials live in a small float
texture, so restyling the city for the frame's weather is one texture upload and each pass is one
or two draw calls:
- colour: 4x multisampled, pyrender's metallic-roughness shading kept verbatim (one directional
  sun, ambient, emission, the same `pow(c, 1/2.2)` output), so previews look as before; fog over
  the ray length and the sky gradient (raster_backend's atmosphere) are applied here too, per
  fragment, instead of in numpy over the finished image (that was ~40 ms a frame);
- ids and depth: not multisampled, an unsigned-integer target, so ids are exact (never averaged at
  edges) and each pixel's depth belongs to the object its id names;
- ids of chosen agents alone (silhouettes): the agents' vertex ranges drawn with one
  glMultiDrawArrays, nothing else.

The context comes from pyrender's EGL platform (headless; llvmpipe needs no GPU). Camera: the
projection is pyrender's IntrinsicsCamera matrix given cx + 0.5, cy + 0.5 (pixel centres at
integers, conventions.md), so pixels land exactly where they did with pyrender.
"""

from __future__ import annotations

import ctypes
import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402
from OpenGL import GL as gl  # noqa: E402

ZNEAR, ZFAR = 0.25, 3000.0
MSAA_SAMPLES = 4
SLOTS_PER_ROW = 1024  # material texture: slot s at (s % 1024, 2 * (s // 1024)) and the row below

_COLOR_VS = """#version 330 core
layout(location = 0) in vec3 position;
layout(location = 1) in vec3 normal;
layout(location = 2) in float slot;
uniform mat4 VP;
uniform sampler2D materials;
out vec3 frag_position;
out vec3 frag_normal;
flat out vec4 base_metal;
flat out vec4 emis_rough;
void main() {
    gl_Position = VP * vec4(position, 1.0);
    frag_position = position;
    frag_normal = normalize(normal);
    int s = int(slot + 0.5);
    ivec2 c = ivec2(s % %SLOTS%, 2 * (s / %SLOTS%));
    base_metal = texelFetch(materials, c, 0);
    emis_rough = texelFetch(materials, c + ivec2(0, 1), 0);
}
""".replace("%SLOTS%", str(SLOTS_PER_ROW))

# pyrender 0.1.45 mesh.frag, metallic-roughness branch with one directional light, no textures.
_COLOR_FS = """#version 330 core
const float PI = 3.141592653589793;
const float min_roughness = 0.04;
in vec3 frag_position;
in vec3 frag_normal;
flat in vec4 base_metal;
flat in vec4 emis_rough;
uniform vec3 cam_pos;
uniform vec3 light_direction;
uniform vec3 light_radiance;
uniform vec3 ambient_light;
uniform int effects;
uniform float fog_density;
uniform vec3 fog_color;
out vec4 frag_color;
void main() {
    float roughness = clamp(emis_rough.a, min_roughness, 1.0);
    float metallic = clamp(base_metal.a, 0.0, 1.0);
    vec3 base = base_metal.rgb;
    vec3 c_diff = mix(vec3(0.0), base * (1 - min_roughness), 1.0 - metallic);
    vec3 f0 = mix(vec3(min_roughness), base, metallic);
    vec3 n = normalize(frag_normal);
    vec3 v = normalize(cam_pos - frag_position);
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
    vec3 color = nl * light_radiance * (diffuse_contrib + spec_contrib);
    color += base * ambient_light;
    color += emis_rough.rgb;
    color = clamp(color, 0.0, 1.0);
    if (effects != 0) {  // fog and haze over the ray length, in linear colour
        float T = exp(-fog_density * length(frag_position - cam_pos));
        color = color * T + fog_color * (1.0 - T);
    }
    frag_color = clamp(vec4(pow(color, vec3(1.0 / 2.2)), 1.0), 0.0, 1.0);
}
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
out vec4 frag_color;
void main() {
    vec2 ndc = 2.0 * gl_FragCoord.xy / viewport - 1.0;
    vec3 d = normalize(ndc_to_world * vec3(ndc, 1.0));
    float e = clamp(d.z, 0.0, 1.0);
    vec3 sky = horizon * (1.0 - e) * (1.0 - e) + zenith * (1.0 - (1.0 - e) * (1.0 - e));
    vec3 c = sky * sky_transmittance + fog_color * (1.0 - sky_transmittance);
    frag_color = vec4(pow(clamp(c, 0.0, 1.0), vec3(1.0 / 2.2)), 1.0);
}
"""

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


def projection(K: np.ndarray, width: int, height: int, znear: float = ZNEAR, zfar: float = ZFAR) -> np.ndarray:
    """OpenGL projection of an OpenCV K (pyrender's IntrinsicsCamera with cx + 0.5, cy + 0.5)."""
    cx, cy = K[0, 2] + 0.5, K[1, 2] + 0.5
    P = np.zeros((4, 4))
    P[0, 0] = 2.0 * K[0, 0] / width
    P[1, 1] = 2.0 * K[1, 1] / height
    P[0, 2] = (width - 2.0 * cx) / width
    P[1, 2] = (2.0 * cy - height) / height
    P[2, 2] = (zfar + znear) / (znear - zfar)
    P[2, 3] = 2.0 * zfar * znear / (znear - zfar)
    P[3, 2] = -1.0
    return P


def view_matrix(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """World -> OpenGL camera (x right, y up, looking down -z) of X_cam = R X_world + t."""
    V = np.eye(4)
    V[:3, :3] = np.diag([1.0, -1.0, -1.0]) @ R
    V[:3, 3] = np.diag([1.0, -1.0, -1.0]) @ np.asarray(t, dtype=np.float64).reshape(3)
    return V


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
    """One vertex array: positions, normals, material slots and (optionally) instance ids."""

    def __init__(self) -> None:
        self.vao = gl.glGenVertexArrays(1)
        self.buffers = list(gl.glGenBuffers(4))
        self.count = 0

    def upload(self, positions: np.ndarray, normals: np.ndarray, slots: np.ndarray, ids: np.ndarray | None) -> None:
        gl.glBindVertexArray(self.vao)
        arrays = [(0, positions, 3), (1, normals, 3), (2, slots, 1), (3, ids, 1)]
        for (loc, data, size), buf in zip(arrays, self.buffers):
            if data is None:
                gl.glDisableVertexAttribArray(loc)
                continue
            data = np.ascontiguousarray(data, dtype=np.float32)
            gl.glBindBuffer(gl.GL_ARRAY_BUFFER, buf)
            gl.glBufferData(gl.GL_ARRAY_BUFFER, data.nbytes, data if data.size else None, gl.GL_STATIC_DRAW)
            gl.glEnableVertexAttribArray(loc)
            gl.glVertexAttribPointer(loc, size, gl.GL_FLOAT, gl.GL_FALSE, 0, ctypes.c_void_p(0))
        gl.glBindVertexArray(0)
        self.count = len(positions)

    def draw(self) -> None:
        if self.count:
            gl.glBindVertexArray(self.vao)
            gl.glDrawArrays(gl.GL_TRIANGLES, 0, self.count)

    def draw_ranges(self, first: np.ndarray, count: np.ndarray) -> None:
        if len(first):
            gl.glBindVertexArray(self.vao)
            gl.glMultiDrawArrays(gl.GL_TRIANGLES, np.ascontiguousarray(first, dtype=np.int32),
                                 np.ascontiguousarray(count, dtype=np.int32), len(first))

    def delete(self) -> None:
        gl.glDeleteBuffers(len(self.buffers), self.buffers)
        gl.glDeleteVertexArrays(1, [self.vao])


class GLRaster:
    """The GL context, programs, framebuffers and the two meshes; see the module doc."""

    def __init__(self) -> None:
        from pyrender.platforms.egl import EGLPlatform

        self._platform = EGLPlatform(1, 1)
        self._platform.init_context()
        self._platform.make_current()
        self._color_prog = _program(_COLOR_VS, _COLOR_FS)
        self._id_prog = _program(_ID_VS, _ID_FS)
        self._sky_prog = _program(_SKY_VS, _SKY_FS)
        self._sky_vao = gl.glGenVertexArrays(1)
        self.static = _Mesh()
        self.agents = _Mesh()
        self._materials = gl.glGenTextures(1)
        self._size: tuple[int, int] | None = None
        self._fbos: list[int] = []
        self._rbos: list[int] = []
        self._loc = {name: gl.glGetUniformLocation(self._color_prog, name)
                     for name in ("VP", "materials", "cam_pos", "light_direction", "light_radiance", "ambient_light",
                                  "effects", "fog_density", "fog_color")}
        self._sky_loc = {name: gl.glGetUniformLocation(self._sky_prog, name)
                         for name in ("ndc_to_world", "viewport", "zenith", "horizon", "fog_color", "sky_transmittance")}
        self._id_loc = {name: gl.glGetUniformLocation(self._id_prog, name) for name in ("VP", "has_ids")}

    def make_current(self) -> None:
        self._platform.make_current()

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

    # -- framebuffers -------------------------------------------------------------------------

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

    def color_pass(self, VP: np.ndarray, cam_pos, light_direction, light_radiance, ambient, width: int, height: int,
                   atmosphere: dict | None = None) -> np.ndarray:
        """The shaded image, (H, W, 3) uint8 (top row first).

        `atmosphere` (None: none; background black): fog_density (1/m), fog_color, zenith and
        horizon (linear rgb), sky_distance (m) and ndc_to_world (3x3, see _SKY_FS).
        """
        self._framebuffers(width, height)
        ms_fb, color_fb, _ = self._fbos
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, ms_fb)
        gl.glViewport(0, 0, width, height)
        self._state()
        gl.glEnable(gl.GL_MULTISAMPLE)
        gl.glClearColor(0.0, 0.0, 0.0, 0.0)
        gl.glClear(gl.GL_COLOR_BUFFER_BIT | gl.GL_DEPTH_BUFFER_BIT)
        gl.glUseProgram(self._color_prog)
        loc = self._loc
        gl.glUniformMatrix4fv(loc["VP"], 1, gl.GL_TRUE, np.asarray(VP, dtype=np.float32))
        gl.glUniform3f(loc["cam_pos"], *(float(x) for x in cam_pos))
        gl.glUniform3f(loc["light_direction"], *(float(x) for x in light_direction))
        gl.glUniform3f(loc["light_radiance"], *(float(x) for x in light_radiance))
        gl.glUniform3f(loc["ambient_light"], *(float(x) for x in ambient))
        gl.glUniform1i(loc["effects"], int(atmosphere is not None))
        if atmosphere is not None:
            gl.glUniform1f(loc["fog_density"], float(atmosphere["fog_density"]))
            gl.glUniform3f(loc["fog_color"], *(float(x) for x in atmosphere["fog_color"]))
        gl.glActiveTexture(gl.GL_TEXTURE0)
        gl.glBindTexture(gl.GL_TEXTURE_2D, self._materials)
        gl.glUniform1i(loc["materials"], 0)
        self.static.draw()
        self.agents.draw()
        if atmosphere is not None:
            self._sky(atmosphere, width, height)
        gl.glBindFramebuffer(gl.GL_READ_FRAMEBUFFER, ms_fb)
        gl.glBindFramebuffer(gl.GL_DRAW_FRAMEBUFFER, color_fb)
        gl.glBlitFramebuffer(0, 0, width, height, 0, 0, width, height, gl.GL_COLOR_BUFFER_BIT, gl.GL_NEAREST)
        gl.glBindFramebuffer(gl.GL_READ_FRAMEBUFFER, color_fb)
        rgba = _read_pixels(width, height, gl.GL_RGBA, gl.GL_UNSIGNED_BYTE, np.uint8, 4)
        gl.glBindFramebuffer(gl.GL_FRAMEBUFFER, 0)
        return rgba[::-1, :, :3]

    def _sky(self, a: dict, width: int, height: int) -> None:
        gl.glUseProgram(self._sky_prog)
        loc = self._sky_loc
        gl.glUniformMatrix3fv(loc["ndc_to_world"], 1, gl.GL_TRUE, np.asarray(a["ndc_to_world"], dtype=np.float32))
        gl.glUniform2f(loc["viewport"], float(width), float(height))
        for name in ("zenith", "horizon", "fog_color"):
            gl.glUniform3f(loc[name], *(float(x) for x in a[name]))
        gl.glUniform1f(loc["sky_transmittance"], float(np.exp(-a["fog_density"] * a["sky_distance"])))
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
        self.static.draw()
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
        gl.glDeleteTextures([self._materials])
        gl.glDeleteProgram(self._color_prog)
        gl.glDeleteProgram(self._id_prog)
        gl.glDeleteProgram(self._sky_prog)
        gl.glDeleteVertexArrays(1, [self._sky_vao])
        from OpenGL.EGL import eglDestroyContext

        # Only this context: terminating the display would invalidate other live contexts.
        eglDestroyContext(self._platform._egl_display, self._platform._egl_context)
        self._platform = None
