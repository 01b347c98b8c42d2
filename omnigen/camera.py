"""The camera: one pinhole in the contract's frames, and its conversions to the renderers' frames.

A `Camera` is K (3x3), R (3x3) and t (3,) with X_cam = R X_world + t in OpenCV's camera axes
(x right, y down, z forward), and the image's width and height in pixels; pixels follow the
contract (the centre of the top-left pixel is (0, 0), omnigen/geometry.py). It is what the rigs
draw (rigs/sampling.py), what the annotator projects cuboids with (rigs/annotate.py) and what
both renderers take (scenes/raster_backend.py, scenes/blender_backend.py).

Why one type and one module: before it, K, R, t, width and height travelled as five loose
arguments through every renderer signature, and each renderer carried its own copy of the one
axis flip between OpenCV's camera and the renderers' cameras. The renderers' frames are met only
here:
- OpenGL and Blender cameras share their axes (x right, y up, looking along -z); OPENCV_TO_OPENGL
  maps OpenCV's camera axes to theirs and, being its own inverse, back;
- the raster backend's view and projection matrices (`gl_view`, `gl_projection`);
- the Blender backend's camera settings (`blender_settings`: lens, sensor width, shifts, with
  sensor_fit AUTO) and its object's matrix_world (`blender_matrix_world`); Blender's own types
  (bpy, mathutils) stay in scenes/blender_backend.py, everything here is plain numpy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from omnigen.conventions import NEAR_PLANE
from omnigen.geometry import is_rotation, project_points

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0])
"""OpenCV's camera looks along +Z with +Y down; OpenGL's and Blender's along -Z with +Y up. The
flip is its own inverse, so it also maps OpenGL/Blender camera axes to OpenCV's."""
OPENCV_TO_OPENGL.setflags(write=False)

BLENDER_SENSOR_WIDTH = 36.0
"""Millimetres: Blender's default sensor width, the one `blender_from_intrinsics` picks."""


# ---------------------------------------------------------------------------------------------
# Intrinsics
# ---------------------------------------------------------------------------------------------


def intrinsics_from_fov(hfov: float, width: int, height: int) -> np.ndarray:
    """K of a centred pinhole with horizontal field of view `hfov` (radians), square pixels."""
    f = (width / 2.0) / math.tan(hfov / 2.0)
    return np.array([[f, 0.0, width / 2.0 - 0.5], [0.0, f, height / 2.0 - 0.5], [0.0, 0.0, 1.0]])


def intrinsics_from_blender(lens: float, sensor_width: float, width: int, height: int,
                            shift_x: float = 0.0, shift_y: float = 0.0) -> np.ndarray:
    """K for a Blender camera with sensor_fit 'AUTO', in the contract's pixel convention.

    f = lens / sensor_width * max(W, H); the principal point sits at the image centre in
    continuous coordinates, which is W/2 - 0.5 when pixel centres are integers.
    """
    size = max(width, height)
    f = lens / sensor_width * size
    cx = width / 2.0 - 0.5 - shift_x * size
    cy = height / 2.0 - 0.5 + shift_y * size
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


def blender_from_intrinsics(K: np.ndarray, width: int, height: int,
                            sensor_width: float = BLENDER_SENSOR_WIDTH) -> dict[str, float]:
    """Blender camera settings (lens, sensor_width, shift_x, shift_y) that reproduce K.

    Blender has one focal length, so fx must equal fy.
    """
    K = np.asarray(K, dtype=np.float64)
    if not math.isclose(K[0, 0], K[1, 1], rel_tol=1e-9):
        raise ValueError(f"Blender cameras need square pixels, got fx={K[0, 0]} fy={K[1, 1]}")
    size = max(width, height)
    return {
        "lens": K[0, 0] * sensor_width / size,
        "sensor_width": sensor_width,
        "shift_x": (width / 2.0 - 0.5 - K[0, 2]) / size,
        "shift_y": (K[1, 2] - height / 2.0 + 0.5) / size,
    }


# ---------------------------------------------------------------------------------------------
# Extrinsics
# ---------------------------------------------------------------------------------------------


def world_to_opencv_camera(camera_to_world_blender: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) with X_cam = R X_world + t, from a Blender camera's 4x4 matrix_world."""
    m = np.asarray(camera_to_world_blender, dtype=np.float64)
    r_wc, c = m[:3, :3], m[:3, 3]
    r = OPENCV_TO_OPENGL @ r_wc.T
    return r, -r @ c


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """(R, t) of an OpenCV camera at `eye` looking at `target`, image up along the world's `up`
    (the contract's world is z up): for placing a camera by hand, in tests and figures."""
    eye, target = np.asarray(eye, float), np.asarray(target, float)
    z = target - eye
    if np.linalg.norm(z) < 1e-12:
        raise ValueError("look_at: the eye is at the target; there is no view direction")
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    norm = np.linalg.norm(x)
    if norm < 1e-9:
        raise ValueError("look_at: the view direction is parallel to `up`; give another up vector")
    x /= norm
    y = np.cross(z, x)
    R = np.stack([x, y, z])
    return R, -R @ eye


def frozen_array(a, shape: tuple[int, ...], name: str) -> np.ndarray:
    """A read-only float64 copy of `a` in `shape`: a frozen camera's arrays cannot be changed
    behind its back (the raster backend keys its per-camera cache on their bytes)."""
    arr = np.array(a, dtype=np.float64)
    if arr.size != math.prod(shape):
        raise ValueError(f"camera {name}: expected {shape}, got shape {arr.shape}")
    arr = arr.reshape(shape)
    if not np.isfinite(arr).all():
        raise ValueError(f"camera {name}: not finite: {arr.tolist()}")
    arr.setflags(write=False)
    return arr


def _pixels(v, name: str) -> int:
    """An image side: a positive whole number (a float such as 160.0 is taken, 160.9 is not)."""
    if isinstance(v, bool) or not float(v).is_integer() or int(v) <= 0:
        raise ValueError(f"camera {name}: must be a positive whole number of pixels, got {v!r}")
    return int(v)


# ---------------------------------------------------------------------------------------------
# The camera
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera in the contract's frames: X_cam = R X_world + t (OpenCV axes), K, and the
    image's size. Immutable; the arrays are read-only float64 copies (t of shape (3,)).

    Equality is identity (eq=False): arrays have no single truth value, and nothing compares
    cameras; compare `K`, `R`, `t` with numpy where needed.
    """

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", frozen_array(self.K, (3, 3), "K"))
        object.__setattr__(self, "R", frozen_array(self.R, (3, 3), "R"))
        object.__setattr__(self, "t", frozen_array(self.t, (3,), "t"))
        if not is_rotation(self.R, tol=1e-5):  # Blender's matrices are float32: ~1e-7 off orthonormal
            raise ValueError(f"camera R: not a rotation (orthonormal, determinant +1): {self.R.tolist()}")
        object.__setattr__(self, "width", _pixels(self.width, "width"))
        object.__setattr__(self, "height", _pixels(self.height, "height"))

    def __reduce__(self):
        """Pickled and copied through the constructor, so a copy's arrays are frozen too (a
        dataclass's default pickling would bypass __post_init__)."""
        return type(self), tuple(getattr(self, f.name) for f in fields(self))

    # -- constructors -----------------------------------------------------------------------

    @classmethod
    def from_fov(cls, hfov: float, R: np.ndarray, t: np.ndarray, width: int, height: int) -> Camera:
        """A centred pinhole (`intrinsics_from_fov`) with horizontal field of view `hfov` (radians)."""
        return cls(intrinsics_from_fov(hfov, width, height), R, t, width, height)

    @classmethod
    def from_blender(cls, matrix_world: np.ndarray, lens: float, width: int, height: int,
                     sensor_width: float = BLENDER_SENSOR_WIDTH, shift_x: float = 0.0, shift_y: float = 0.0) -> Camera:
        """The camera a Blender camera object renders with (sensor_fit AUTO): its 4x4 matrix_world
        (Blender camera axes) and its lens, sensor width and shifts."""
        R, t = world_to_opencv_camera(matrix_world)
        return cls(intrinsics_from_blender(lens, sensor_width, width, height, shift_x, shift_y), R, t, width, height)

    # -- the contract's frames --------------------------------------------------------------

    @property
    def center(self) -> np.ndarray:
        """The camera's centre in the world: -R^T t."""
        return -self.R.T @ self.t

    def to_camera(self, points_world: np.ndarray) -> np.ndarray:
        """World points (..., 3) in this camera's frame: R X + t, the same shape."""
        return np.asarray(points_world, dtype=np.float64) @ self.R.T + self.t

    def project(self, points_world: np.ndarray, near: float = NEAR_PLANE) -> tuple[np.ndarray, np.ndarray]:
        """World points (N, 3) to pixels: (uv (N, 2), behind (N,)) as `geometry.project_points`
        gives them for the points in this camera's frame (NaN where closer than `near`)."""
        return project_points(self.K, self.to_camera(points_world), near)

    # -- OpenGL (the raster backend) -------------------------------------------------------

    def gl_view(self) -> np.ndarray:
        """4x4 world -> OpenGL camera (x right, y up, looking down -z)."""
        V = np.eye(4)
        V[:3, :3] = OPENCV_TO_OPENGL @ self.R
        V[:3, 3] = OPENCV_TO_OPENGL @ self.t
        return V

    def gl_projection(self, znear: float, zfar: float) -> np.ndarray:
        """4x4 OpenGL projection of K: pyrender's IntrinsicsCamera given cx + 0.5, cy + 0.5, since
        OpenGL measures the principal point from the image's corner and the contract from the
        top-left pixel's centre (conventions.md, "Measured facts about the renderers")."""
        K, width, height = self.K, self.width, self.height
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

    # -- Blender (the Cycles backend) -------------------------------------------------------

    def blender_settings(self, sensor_width: float = BLENDER_SENSOR_WIDTH) -> dict[str, float]:
        """lens, sensor_width, shift_x, shift_y of the Blender camera (sensor_fit AUTO) with this K."""
        return blender_from_intrinsics(self.K, self.width, self.height, sensor_width)

    def blender_matrix_world(self) -> np.ndarray:
        """4x4 camera-to-world in Blender camera axes: a Blender camera object's matrix_world."""
        m = np.eye(4)
        m[:3, :3] = self.R.T @ OPENCV_TO_OPENGL
        m[:3, 3] = self.center
        return m
